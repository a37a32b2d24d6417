"""``python -m diffcam`` is the ``diffcam`` command."""
import sys

from diffcam.apps.cli import main

sys.exit(main())
