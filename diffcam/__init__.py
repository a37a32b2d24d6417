"""diffcam: differentiable JAX optics for lensless diffuser cameras."""
__version__ = "0.1.0"
