"""``generate --jpeg-decoder gpu`` (gpu_blur/gpu_jpeg.py): JPEG inputs decoded in groups on the
GPU, everything else the CPU's way.

The plumbing runs everywhere torch is installed, with a stand-in for nvJPEG that returns the
CPU decoder's pixels as torch CPU tensors: the set must then be the CPU run's, byte for byte.
nvJPEG itself runs only where torch sees CUDA and torchvision imports (the GPU host).
"""

import json
import sys
import types

import cv2
import numpy as np
import pytest
from conftest import KERNEL_BACKEND_SPECS, manifest_lines

import gpu_blur.gpu_jpeg
from gpu_blur import generate_set
from gpu_blur.cli import main
from gpu_blur.dataset import LOCK
from gpu_blur.gpu_jpeg import (
    NVJPEG_MAX_DIFFERENCE,
    NVJPEG_MEAN_DIFFERENCE,
    JpegBatches,
    for_backend,
    nvjpeg_size,
)
from gpu_blur.image_reading import read_image

torch = pytest.importorskip("torch")

AVERAGE = '[blur]\nmode = "average"\nframes = 3\n'
#: numpy and the first device of each kernel backend (Warp takes torch tensors where they lie,
#: as on CUDA)
BACKENDS = ["numpy", *{spec.split(":")[0]: spec.split("/")[0]
                       for spec in reversed(KERNEL_BACKEND_SPECS)}.values()]
SAMPLING = {"420": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_420,
            "444": cv2.IMWRITE_JPEG_SAMPLING_FACTOR_444}


def write_jpeg(path, rgb, sampling="420", progressive=False):
    params = [cv2.IMWRITE_JPEG_QUALITY, 90, cv2.IMWRITE_JPEG_SAMPLING_FACTOR, SAMPLING[sampling],
              cv2.IMWRITE_JPEG_PROGRESSIVE, int(progressive)]
    assert cv2.imwrite(str(path), np.ascontiguousarray(rgb[..., ::-1]), params)


def cpu_pixels(files, device):
    """The stand-in for nvJPEG: OpenCV's pixels (read_image's), 3 x H x W torch CPU tensors."""
    assert device == "cpu"
    return [torch.from_numpy(cv2.imdecode(f, cv2.IMREAD_UNCHANGED)[..., ::-1].copy())
            .permute(2, 0, 1) for f in files]


@pytest.fixture
def stand_in(monkeypatch):
    """``--jpeg-decoder gpu`` on any backend, decoding with :func:`cpu_pixels`; its batches."""
    made = []

    def batches(backend, frames):
        made.append(JpegBatches("cpu", frames, decode=cpu_pixels))
        return made[-1]

    monkeypatch.setattr(gpu_blur.gpu_jpeg, "for_backend", batches)
    return made


@pytest.fixture
def sequences(tmp_path):
    """Sequences of 6 frames of 24 x 32 (2 windows of 3 each): JPEG (4:2:0, 4:4:4,
    progressive), PNG, and PNG and JPEG mixed."""
    folder = tmp_path / "seqs"
    rng = np.random.default_rng(3)
    kinds = {"a_jpeg": "420", "b_jpeg444": "444", "c_png": "png", "d_mixed": "mixed",
             "e_jpeg": "420", "f_progressive": "progressive"}
    for name, kind in kinds.items():
        frames = folder / name / "sharp"
        frames.mkdir(parents=True)
        for i in range(6):
            frame = rng.integers(0, 256, (24, 32, 3), np.uint8)
            if kind == "png" or (kind == "mixed" and i % 2):
                cv2.imwrite(str(frames / f"{i}.png"), frame[..., ::-1])
            else:
                write_jpeg(frames / f"{i}.jpg", frame, "444" if kind == "444" else "420",
                           progressive=kind == "progressive")
    scene = tmp_path / "avg.toml"
    scene.write_text(AVERAGE)
    return folder, scene


def args(folder, scene, out, *extra):
    return ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--quiet", *extra]


def sample_files(out):
    """{relative path: bytes} of every file of a set but its manifest, run.json and lock."""
    return {p.relative_to(out).as_posix(): p.read_bytes() for p in sorted(out.rglob("*"))
            if p.is_file() and p.name not in (LOCK, "manifest.jsonl", "run.json")}


def without_decoder(lines):
    return [{k: v for k, v in line.items() if k != "jpeg_decoder"} for line in lines]


def assert_cpu_runs_set(out, reference):
    """The set in ``out`` is the CPU run's in ``reference``: the same files, byte for byte,
    and the same manifest but for the decoder named on the lines decoded on the GPU."""
    assert sample_files(out) == sample_files(reference)
    assert without_decoder(manifest_lines(out)) == manifest_lines(reference)


@pytest.mark.parametrize("backend", BACKENDS)
def test_the_gpu_path_with_the_cpu_decoders_pixels_writes_the_cpu_runs_bytes(
        tmp_path, sequences, stand_in, backend):
    folder, scene = sequences
    run = ["--backend", backend.split("/")[0], "--io-threads", "3"]
    assert main(args(folder, scene, tmp_path / "cpu", *run)) == 0
    assert main(args(folder, scene, tmp_path / "gpu", *run, "--jpeg-decoder", "gpu")) == 0
    assert_cpu_runs_set(tmp_path / "gpu", tmp_path / "cpu")
    decoded = {x["name"]: x.get("jpeg_decoder") for x in manifest_lines(tmp_path / "gpu")}
    # all-JPEG baseline samples went through the stand-in, in groups; the rest the CPU's way
    assert {n.split("/")[0] for n, d in decoded.items() if d == "gpu"} == {
        "a_jpeg", "b_jpeg444", "e_jpeg"}
    (batches,) = stand_in
    assert len(batches.gpu) == 6 and batches.files == 18 and batches.cpu == 2  # progressive
    record = json.loads((tmp_path / "gpu" / "run.json").read_text())
    assert record["jpeg_decoder"] == "gpu"
    assert "jpeg_decoder" not in json.loads((tmp_path / "cpu" / "run.json").read_text())


def test_photos_of_jpeg_go_in_groups_as_one_photo_batches(tmp_path, stand_in):
    folder = tmp_path / "photos"
    folder.mkdir()
    rng = np.random.default_rng(4)
    for i in range(5):
        write_jpeg(folder / f"{i}.jpg", rng.integers(0, 256, (24 + 8 * (i % 2), 32, 3),
                                                       np.uint8))
    scene = tmp_path / "s.toml"
    scene.write_text("[blur]\nsteps = 3\n")
    assert main(args(folder, scene, tmp_path / "cpu", "--io-threads", "2")) == 0
    assert main(args(folder, scene, tmp_path / "gpu", "--io-threads", "2",
                     "--jpeg-decoder", "gpu")) == 0
    assert_cpu_runs_set(tmp_path / "gpu", tmp_path / "cpu")
    assert len(stand_in[0].gpu) == 5  # two sizes in a group: a batch each


def test_a_bad_jpeg_among_good_ones_fails_its_sample_naming_the_file(tmp_path, sequences,
                                                                     stand_in):
    folder, scene = sequences
    bad = folder / "a_jpeg" / "sharp" / "1.jpg"
    bad.write_bytes(bad.read_bytes()[:300])
    run = ["--io-threads", "3"]
    assert main(args(folder, scene, tmp_path / "cpu", *run)) == 1
    assert main(args(folder, scene, tmp_path / "gpu", *run, "--jpeg-decoder", "gpu")) == 1
    assert_cpu_runs_set(tmp_path / "gpu", tmp_path / "cpu")
    failed = [x for x in manifest_lines(tmp_path / "gpu") if x["status"] == "failed"]
    assert [x["name"] for x in failed] == ["a_jpeg/0"]
    assert failed[0]["error"].startswith(f"{bad}: truncated JPEG")
    assert "jpeg_decoder" not in failed[0]


def test_a_failed_group_decode_makes_its_samples_on_the_cpu(tmp_path, sequences, monkeypatch):
    def failing(files, device):
        raise RuntimeError("nvjpegDecodeBatched failed")

    monkeypatch.setattr(gpu_blur.gpu_jpeg, "for_backend",
                        lambda backend, frames: JpegBatches("cpu", frames, decode=failing))
    folder, scene = sequences
    assert main(args(folder, scene, tmp_path / "cpu", "--io-threads", "2")) == 0
    assert main(args(folder, scene, tmp_path / "gpu", "--io-threads", "2",
                     "--jpeg-decoder", "gpu")) == 0
    assert_cpu_runs_set(tmp_path / "gpu", tmp_path / "cpu")
    assert not any("jpeg_decoder" in x for x in manifest_lines(tmp_path / "gpu"))


def test_mixed_png_and_jpeg_samples_are_decoded_on_the_cpu(tmp_path, sequences, stand_in):
    folder, scene = sequences
    assert main(args(folder, scene, tmp_path / "gpu", "--io-threads", "2",
                     "--jpeg-decoder", "gpu", "--limit", "8")) == 0
    lines = {x["name"]: x.get("jpeg_decoder") for x in manifest_lines(tmp_path / "gpu")}
    assert lines["d_mixed/0"] is None and lines["c_png/0"] is None
    assert lines["a_jpeg/0"] == "gpu"


def test_a_resume_with_another_jpeg_decoder_is_refused(tmp_path, sequences, stand_in, capsys):
    folder, scene = sequences
    out = tmp_path / "set"
    run = ["--io-threads", "2", "--limit", "2"]
    assert main(args(folder, scene, out, *run, "--jpeg-decoder", "gpu")) == 0
    assert main(args(folder, scene, out, *run, "--resume")) == 2
    error = capsys.readouterr().err
    assert "was made with another --jpeg-decoder: jpeg_decoder = 'gpu' (this run: None)" in error
    assert main(args(folder, scene, out, *run, "--resume", "--jpeg-decoder", "gpu")) == 0

    cpu = tmp_path / "cpu"
    assert main(args(folder, scene, cpu, *run)) == 0
    assert main(args(folder, scene, cpu, *run, "--resume", "--jpeg-decoder", "gpu")) == 2
    assert "another --jpeg-decoder: jpeg_decoder = None (this run: 'gpu')" in (
        capsys.readouterr().err)


def test_the_gpu_decoder_is_refused_off_a_cuda_backend(tmp_path, sequences, capsys):
    folder, scene = sequences
    assert main(args(folder, scene, tmp_path / "out", "--jpeg-decoder", "gpu",
                     "--io-threads", "2")) == 2
    error = capsys.readouterr().err
    assert "--jpeg-decoder gpu: the backend runs on numpy" in error
    assert "not a CUDA GPU" in error and "--backend warp:cuda:N" in error
    assert "leave --jpeg-decoder at cpu" in error
    assert not (tmp_path / "out").exists()  # refused before the set was opened


def cuda_backend():
    return types.SimpleNamespace(name="warp", wp_device="cuda:0",
                                 device="warp:cuda:0 NVIDIA H100, float32")


def test_the_gpu_decoder_is_refused_without_torchvision(monkeypatch):
    monkeypatch.setitem(sys.modules, "torchvision", None)  # its import fails
    with pytest.raises(ValueError, match=r"--jpeg-decoder gpu needs torch and torchvision "
                       r"\(decode_jpeg runs nvJPEG\), and importing them failed "
                       r"\(ModuleNotFoundError: .*\): pip install torchvision built for the "
                       r"installed torch, or leave --jpeg-decoder at cpu"):
        for_backend(cuda_backend(), True)


def test_the_gpu_decoder_is_refused_where_torch_sees_no_cuda(monkeypatch):
    fake = types.ModuleType("torchvision")
    fake.io = types.ModuleType("torchvision.io")
    monkeypatch.setitem(sys.modules, "torchvision", fake)
    monkeypatch.setitem(sys.modules, "torchvision.io", fake.io)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    with pytest.raises(ValueError, match=r"--jpeg-decoder gpu: torch .* sees no CUDA device .*"
                       r"install torch and torchvision built for CUDA, or leave"):
        for_backend(cuda_backend(), True)


@pytest.mark.parametrize(("given", "words"), [
    ({"devices": "numpy,numpy"}, "decodes in a run on one device, not with --devices"),
    ({"io_threads": 1}, "--io-threads 2 or more"),
    ({"jpeg_decoder": "nvjpeg"}, "--jpeg-decoder nvjpeg: not a decoder; give one of cpu, gpu"),
])
def test_the_gpu_decoder_is_refused_outside_the_one_device_pipeline(tmp_path, given, words):
    given = {"jpeg_decoder": "gpu", **given}
    with pytest.raises(ValueError, match=words):
        generate_set(tmp_path / "out", **given)


def test_only_baseline_ycbcr_jpegs_go_to_nvjpeg(tmp_path):
    rgb = np.random.default_rng(5).integers(0, 256, (24, 40, 3), np.uint8)
    for sampling in SAMPLING:
        write_jpeg(tmp_path / f"{sampling}.jpg", rgb, sampling)
        assert nvjpeg_size((tmp_path / f"{sampling}.jpg").read_bytes()) == (40, 24)
    write_jpeg(tmp_path / "p.jpg", rgb, progressive=True)
    cv2.imwrite(str(tmp_path / "grey.jpg"), rgb[..., 0])
    cv2.imwrite(str(tmp_path / "a.png"), rgb)
    for name in ("p.jpg", "grey.jpg", "a.png"):
        assert nvjpeg_size((tmp_path / name).read_bytes()) is None, name
    # a file that is not for nvJPEG is decoded in its I/O thread, to read_image's pixels
    assert np.array_equal(JpegBatches.read(tmp_path / "p.jpg"), read_image(tmp_path / "p.jpg"))
    assert JpegBatches.read(tmp_path / "420.jpg").ndim == 1


def nvjpeg_ready() -> bool:
    try:
        import torchvision.io  # noqa: F401
    except Exception:
        return False
    return torch.cuda.is_available()


@pytest.mark.skipif(not nvjpeg_ready(), reason="nvJPEG needs torch with CUDA and torchvision")
@pytest.mark.parametrize("sampling", list(SAMPLING))
def test_nvjpeg_pixels_lie_within_the_tolerance_of_opencvs(tmp_path, sampling):
    from gpu_blur.discovery import default_photo

    photo = cv2.resize(read_image(default_photo()), (1920, 1200),
                       interpolation=cv2.INTER_CUBIC)
    write_jpeg(tmp_path / "a.jpg", photo, sampling)
    data = np.frombuffer((tmp_path / "a.jpg").read_bytes(), np.uint8)
    (gpu,) = gpu_blur.gpu_jpeg.nvjpeg_decode([data], "cuda:0")
    gpu = gpu.permute(1, 2, 0).cpu().numpy().astype(int)
    difference = np.abs(gpu - read_image(tmp_path / "a.jpg").astype(int))
    assert difference.max() <= NVJPEG_MAX_DIFFERENCE, difference.max()
    assert difference.mean() <= NVJPEG_MEAN_DIFFERENCE, difference.mean()


@pytest.mark.skipif(not nvjpeg_ready(), reason="nvJPEG needs torch with CUDA and torchvision")
def test_a_cuda_run_decodes_its_jpeg_samples_with_nvjpeg(tmp_path, sequences):
    folder, scene = sequences
    run = ["--backend", "warp:cuda:0", "--io-threads", "3"]
    assert main(args(folder, scene, tmp_path / "cpu", *run)) == 0
    assert main(args(folder, scene, tmp_path / "gpu", *run, "--jpeg-decoder", "gpu")) == 0
    lines = manifest_lines(tmp_path / "gpu")
    assert sum(x.get("jpeg_decoder") == "gpu" for x in lines) == 6
    assert [(x["name"], x["status"]) for x in lines] == [
        (x["name"], x["status"]) for x in manifest_lines(tmp_path / "cpu")]
    libraries = json.loads((tmp_path / "gpu" / "run.json").read_text())["libraries"]
    assert "torchvision" in libraries and "cuda" in libraries
