"""The OpenCL ICD loader path gpu_blur sets up: never a folder another user could write."""

import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import pytest

pytest.importorskip("pyopencl")

INTEL = Path(sys.prefix) / "lib" / "libintelocl.so"
needs_intel = pytest.mark.skipif(not INTEL.is_file(), reason="Intel's CPU runtime from PyPI is "
                                 "not installed in this prefix: gpu_blur registers nothing")

#: Imports the backend in a fresh process and prints what the loader was pointed at.
PROBE = """
import json, os, stat
import gpu_blur.backends.opencl as ocl
folder = os.environ.get("OCL_ICD_VENDORS")
st = os.lstat(folder) if folder and os.path.exists(folder) else None
print(json.dumps({"folder": folder, "mode": st and stat.S_IMODE(st.st_mode),
                  "uid": st and st.st_uid,
                  "files": sorted(os.listdir(folder)) if st else None,
                  "platforms": sorted({d.platform for d in ocl.opencl_devices()})}))
"""


def _probe(env: dict) -> dict:
    clean = {k: v for k, v in os.environ.items()
             if k not in ("OCL_ICD_VENDORS", "GPU_BLUR_ICD_FOLDER")}
    out = subprocess.run([sys.executable, "-c", PROBE], env={**clean, **env},
                         capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


@needs_intel
def test_the_vendor_folder_is_fresh_private_and_removed_at_exit():
    first, second = _probe({}), _probe({})
    assert first["folder"] != second["folder"]  # a new, unpredictable name per process
    assert first["mode"] == 0o700 and first["uid"] == os.getuid()
    assert "gpu_blur-intel-cpu.icd" in first["files"]
    assert "Intel(R) OpenCL" in first["platforms"]
    assert not Path(first["folder"]).exists()  # removed when the process ended


@needs_intel
def test_a_folder_planted_under_the_old_predictable_name_is_not_used(tmp_path):
    import hashlib

    old = Path(tempfile.gettempdir()) / (
        f"gpu_blur-icd-{os.getuid()}-{hashlib.sha256(sys.prefix.encode()).hexdigest()[:12]}")
    made = not old.exists()
    if made:
        old.mkdir(mode=0o777)
    try:
        (old / "planted.icd").write_text(str(tmp_path / "libplanted.so") + "\n")
        seen = _probe({})
        assert Path(seen["folder"]) != old and "planted.icd" not in seen["files"]
    finally:
        (old / "planted.icd").unlink(missing_ok=True)
        if made:
            old.rmdir()


@needs_intel
def test_an_inherited_folder_that_others_can_write_is_replaced(tmp_path):
    shared = tmp_path / "vendors"
    shared.mkdir()
    shared.chmod(0o777)
    (shared / "planted.icd").write_text(str(tmp_path / "libplanted.so") + "\n")
    seen = _probe({"OCL_ICD_VENDORS": str(shared), "GPU_BLUR_ICD_FOLDER": str(shared)})
    assert Path(seen["folder"]) != shared and seen["mode"] == 0o700
    assert "planted.icd" not in seen["files"]


@needs_intel
def test_an_inherited_private_folder_is_reused_by_the_child():
    parent = Path(tempfile.mkdtemp(prefix="gpu_blur-icd-"))
    try:
        (parent / "gpu_blur-intel-cpu.icd").write_text(f"{INTEL}\n")
        seen = _probe({"OCL_ICD_VENDORS": str(parent), "GPU_BLUR_ICD_FOLDER": str(parent)})
        assert Path(seen["folder"]) == parent and "Intel(R) OpenCL" in seen["platforms"]
    finally:
        for f in parent.iterdir():
            f.unlink()
        parent.rmdir()


def test_a_loader_path_the_user_set_is_left_alone(tmp_path):
    seen = _probe({"OCL_ICD_VENDORS": str(tmp_path)})
    assert seen["folder"] == str(tmp_path)
