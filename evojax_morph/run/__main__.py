"""`python -m evojax_morph.run`: see `evojax_morph.run.cli`."""

import sys

from evojax_morph.run.cli import main

sys.exit(main())
