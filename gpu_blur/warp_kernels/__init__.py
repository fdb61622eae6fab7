"""NVIDIA Warp device functions and kernels of the Warp backend."""
