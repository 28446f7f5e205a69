"""twinbench: evaluate robot manipulation policies in photorealistic digital twins."""

__version__ = "0.1.0"
