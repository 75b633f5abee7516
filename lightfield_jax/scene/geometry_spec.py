"""A geometry as users write it: parsed from a config's or capture's ``geometry:`` key
(:func:`parse_geometry`) or a fit result's ``model.geometry`` (:func:`parse_fitted_geometry`),
and described in words (:func:`describe_geometry`)."""

from __future__ import annotations

from lightfield_jax.scene.geometry import (
    AutoGeometry,
    Plane,
    Slab,
    positive_finite,
)


def parse_geometry(spec, where: str = "geometry", allow_auto: bool = False):
    """``geometry:`` of a simulate config or a capture file (absent: the plane).

    ``kind: auto`` (captures only, ``allow_auto``) takes the slab's keys and an
    optional ``threshold``; the fit chooses plane or slab (:class:`AutoGeometry`)."""
    if spec is None:
        return Plane()
    if not isinstance(spec, dict):
        raise ValueError(f"{where}: must be a mapping with 'kind', got {spec!r}")
    kind = spec.get("kind", "plane")
    if not isinstance(kind, str):
        raise ValueError(f"{where}.kind: must be a string (plane, slab), got {kind!r}")
    if "kind" not in spec and "thickness" in spec:
        raise ValueError(f"{where}.kind: missing (a slab needs kind: slab with its thickness)")
    slab_keys = {"kind", "thickness", "boundary", "n", "n_mu", "n_z", "depth_profile"}
    allowed = {"plane": {"kind"}, "slab": slab_keys}
    if allow_auto:
        allowed["auto"] = slab_keys | {"threshold"}
    if kind not in allowed:
        raise ValueError(
            f"{where}.kind: must be {' or '.join(repr(k) for k in allowed)}, got {kind!r}"
            + ("" if allow_auto or kind != "auto" else " (auto is for fits: a capture file)")
        )
    unknown = sorted(set(spec) - allowed[kind])
    if unknown:
        raise ValueError(
            f"{where}.{unknown[0]}: unknown key for kind {kind!r}; allowed keys: "
            f"{', '.join(sorted(allowed[kind]))}"
        )
    if kind == "plane":
        return Plane()
    if "thickness" not in spec:
        why = "the slab it may choose" if kind == "auto" else "kind 'slab'"
        raise ValueError(f"{where}.thickness: required for {why} (the tank's depth in pixels)")
    boundary = spec.get("boundary", "absorbing")
    if "n" in spec and boundary != "refractive":
        raise ValueError(f"{where}.n: only meaningful with boundary 'refractive'")
    try:
        slab = Slab(
            thickness=spec["thickness"],
            boundary=boundary,
            n=spec.get("n", 1.33),
            n_mu=spec.get("n_mu"),
            n_z=spec.get("n_z"),
            depth_profile=spec.get("depth_profile"),
        )
    except ValueError as err:
        raise ValueError(str(err).replace("geometry", where, 1)) from None
    if kind == "slab":
        return slab
    threshold = positive_finite(spec.get("threshold", 1.0), f"{where}.threshold")
    return AutoGeometry(slab, threshold)


def parse_fitted_geometry(spec, where: str = "model.geometry"):
    """The geometry of a fit result's ``model`` (:func:`parse_geometry`). A slab with
    ``n_z`` and no ``depth_profile`` comes from a result file without that key, whose
    layers each keep their average: it is read as ``"constant"`` (the model that was
    fitted)."""
    if isinstance(spec, dict) and spec.get("kind") == "slab":
        if spec.get("n_z") is not None and "depth_profile" not in spec:
            spec = {**spec, "depth_profile": "constant"}
    return parse_geometry(spec, where)


def describe_geometry(model: dict) -> str:
    """A short description of a fit result's ``model`` geometry (and auto's choice)."""
    geo = model.get("geometry") or {"kind": "plane"}
    if geo.get("kind") == "slab":
        text = f"slab h {geo['thickness']:g} px {geo['boundary']}"
        if geo["boundary"] == "refractive":
            text += f" n {geo['n']:g}"
        text += f", n_mu {geo.get('n_mu')}, n_z {geo.get('n_z', 1)}"
        if geo.get("depth_profile") == "linear":
            text += " (linear in depth)"
    else:
        text = "plane"
    choice = model.get("geometry_choice")
    if choice and "reason" in choice:
        text += f" (auto: {choice['reason']})"
    elif choice:
        text += f" (auto: plane error {choice['plane_error']:.2g} vs noise {choice['noise']:.2g})"
    return text


__all__ = [
    "describe_geometry",
    "parse_geometry",
]
