"""``python -m diffcam`` is the ``diffcam`` command."""
import sys

from .cli import main

sys.exit(main())
