"""What runs the library end to end: the command line (:mod:`.cli`), the demo
(:mod:`.demo`) and the paper's experiments (:mod:`.paper`)."""

from diffcam.core.lazy import attach_stub

__getattr__, __dir__ = attach_stub(__name__, __file__)[:2]   # submodules on first access
