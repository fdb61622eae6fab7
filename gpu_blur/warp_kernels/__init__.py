"""NVIDIA Warp device functions and kernels of the Warp backend."""

__all__: list[str] = []
