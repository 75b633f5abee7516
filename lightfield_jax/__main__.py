"""``python -m lightfield_jax``: the ``lightfield-jax`` command line."""

import sys

from ._cli import main

sys.exit(main())
