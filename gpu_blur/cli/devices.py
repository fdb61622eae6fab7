"""``gpu-blur devices``: every backend and device, with fp64 support and memory."""

from __future__ import annotations

__all__ = ["add_parser", "run"]


def add_parser(sub) -> None:
    """The subcommand (no options)."""
    sub.add_parser("devices", help="list every backend and device, with fp64 support and memory")


def run(args) -> int:
    """Print one line per device."""
    _devices()
    return 0


def _devices() -> None:
    from gpu_blur.backends.numpy import NumpyBackend

    print(f"{'numpy':<16} {NumpyBackend.device}")
    try:
        from gpu_blur.backends.opencl import NO_PLATFORM_HELP, opencl_devices
    except ImportError:
        print("opencl           not installed (pip install 'gpu_blur[opencl]')")
        devices = []
    else:
        devices = opencl_devices()
        if not devices:
            print(f"opencl           {NO_PLATFORM_HELP}")
    for d in devices:
        state = "ready" if d.usable else f"cannot build kernels: {d.problem}"
        print(f"{d.spec:<16} {d.kind} {d.name} ({d.platform}); fp64 {'yes' if d.fp64 else 'no'}"
              f"; {d.memory_bytes / 2**30:.1f} GiB; {state}")
    try:
        from gpu_blur.backends.warp import warp_devices
    except ImportError:
        print("warp             not installed (pip install 'gpu_blur[warp]')")
        return
    for d in warp_devices():
        memory = f"; {d['memory_bytes'] / 2**30:.1f} GiB" if d["memory_bytes"] else ""
        print(f"{d['spec']:<16} {d['kind']} {d['name']} (NVIDIA Warp); fp64 yes{memory}; ready")

