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
    orig = list(getattr(sys, "orig_argv", []))
    module = "-m" in orig and orig[orig.index("-m") + 1 :][:1] == ["lightfield_jax"]
    return module or name.startswith("lightfield-jax")


def _import_jax() -> None:
    try:
        import jax  # noqa: F401
    except ValueError as e:
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
