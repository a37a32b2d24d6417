"""``python -m diffcam`` is the ``diffcam`` command."""
from diffcam.apps.cli import run

run()
