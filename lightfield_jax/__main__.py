"""``python -m lightfield_jax``: the ``lightfield-jax`` command line."""

import sys

from lightfield_jax.app.cli import main

sys.exit(main())
