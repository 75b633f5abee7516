"""JAX imported with its environment checked: a ``JAX_*`` variable that JAX cannot read
(``JAX_COMPILATION_CACHE_MAX_SIZE=2G``, ``JAX_ENABLE_X64=maybe``) fails JAX's import
with a traceback that names a flag, not always the variable. Imported first by the
package (importing this module imports JAX): the command line says it in one line
(exit status 2), the API raises an ``ImportError`` that names the variables set."""

from __future__ import annotations

import os
import sys


def _command_line() -> bool:
    """Whether this process is the ``lightfield-jax`` command (or ``python -m``)."""
    name = os.path.basename(sys.argv[0]) if sys.argv and sys.argv[0] else ""
    if name.startswith("lightfield-jax"):
        return True
    # python -m lightfield_jax (sys.argv[0] is "-m" while the package is imported): the
    # module named by -m, or -mlightfield_jax, before any script.
    orig = list(getattr(sys, "orig_argv", []))[1:]
    for i, arg in enumerate(orig):
        if arg == "-m":
            return orig[i + 1 : i + 2] == ["lightfield_jax"]
        if arg.startswith("-m"):
            return arg == "-mlightfield_jax"
        if not arg.startswith("-"):
            return False  # a script
    return False


def _import_jax() -> None:
    try:
        import jax  # noqa: F401
    except ValueError as e:
        if not any(k.startswith("JAX_") for k in os.environ):
            raise  # (not the environment's: a broken installation)
        given = ", ".join(
            f"{k}={v!r}" for k, v in sorted(os.environ.items()) if k.startswith("JAX_")
        )
        message = (
            f"JAX cannot start: {' '.join(str(e).split())} (its environment: {given or 'none'};"
            " correct or unset the variable)"
        )
        if _command_line():
            print(f"lightfield-jax: error: {message}", file=sys.stderr)
            raise SystemExit(2) from None
        raise ImportError(f"lightfield_jax: {message}") from None


_import_jax()
