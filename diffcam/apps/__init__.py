"""What runs the library end to end: the command line (`diffcam.apps.cli`), the demo
(`diffcam.apps.demo`) and the paper's experiments (`diffcam.apps.paper`)."""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__ = attach_stub(__name__, __file__)[:2]   # submodules on first access
