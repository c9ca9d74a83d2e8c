"""occflownet: camera-only 3D semantic occupancy trained by differentiable rendering (OccFlowNet).

Importing the package is cheap and does not import torch; submodules that need torch import it themselves.
"""
__version__ = "0.1.0"
