"""``python -m sb3_sfgpi.cli``: the same as the ``sb3-sfgpi`` console script."""

import sys

from sb3_sfgpi.cli import main

sys.exit(main())
