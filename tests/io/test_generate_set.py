import json

import pytest

import gpu_blur
from gpu_blur.backends import get_backend
from gpu_blur.cli import main
from gpu_blur.timings import CATEGORIES


def files(folder):
    """Every file of a set by its path in the folder, but the lock (it names the process)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file() and p.name != ".gpu_blur.lock"}


@pytest.mark.slow
def test_generate_set_reports_and_writes_the_clis_set(tmp_path, capsys, quick_scene):
    # the built-in photo (no input given to either), the default chain with 3 camera poses
    out, seen = tmp_path / "api", []
    report = gpu_blur.generate_set(out, limit=2, seed=3, backend="numpy", io_threads=1,
                                   scene=quick_scene,
                                   progress=lambda done, total: seen.append((done, total)))
    assert capsys.readouterr() == ("", "")  # nothing printed: the report says it
    assert (report.made, report.failed, report.skipped, report.to_make) == (2, (), 0, 2)
    assert seen == [(1, 2), (2, 2)]
    assert report.output == out and report.manifest == out / "manifest.jsonl"
    assert report.device == get_backend("numpy").device
    assert report.seconds > 0 and set(report.timings) == set(CATEGORIES)
    assert report.bound.startswith("bound by: ") and report.summary[-1] == report.bound
    assert report.summary[0].startswith(f"wrote 2 samples (0 failed) to {out} in ")
    lines = [json.loads(x) for x in report.manifest.read_text().splitlines()]
    assert [(x["index"], x["status"]) for x in lines] == [(0, "ok"), (1, "ok")]
    for line in lines:
        assert (out / line["blurred"]).is_file() and (out / line["sharp"]).is_file()
    assert json.loads((out / "run.json").read_text())["seed"] == 3

    cli = tmp_path / "cli"
    assert main(["generate", "--output", str(cli), "--limit", "2", "--seed", "3", "--backend",
                 "numpy", "--io-threads", "1", "--scene", str(quick_scene), "--quiet"]) == 0
    assert capsys.readouterr().out.splitlines()[0].startswith("wrote 2 samples (0 failed)")
    assert files(out) == files(cli)  # byte for byte, run.json and manifest included
    assert len(files(out)) > 4

    # resume finds the set done; a new run is refused as the command refuses it
    states = []
    again = gpu_blur.generate_set(out, limit=2, seed=3, scene=quick_scene, resume=True,
                                  on_resume=states.append)
    assert (again.made, again.skipped, again.to_make) == (0, 2, 0)
    assert [(s.done, s.samples, s.to_make) for s in states] == [(2, 2, 0)]
    assert files(out) == files(cli)
    with pytest.raises(ValueError, match="--overwrite"):
        gpu_blur.generate_set(out, limit=2, seed=3, scene=quick_scene)


def test_generate_set_raises_what_the_command_prints(tmp_path, capsys):
    devices = []
    with pytest.raises(ValueError, match=r"--seed -1: must lie in \[0, 2\*\*64\)"):
        gpu_blur.generate_set(tmp_path / "set", seed=-1, on_device=devices.append)
    assert devices == []  # the options are checked before the device is opened
    gpu_blur.generate_set(tmp_path / "set", limit=1, scene={"blur": {"steps": 3}},
                          on_device=devices.append)
    assert devices == [get_backend("numpy").device]
    with pytest.raises(ValueError, match="--save shiny: 'shiny' is not an output"):
        gpu_blur.generate_set(tmp_path / "set", save=["shiny"])
    with pytest.raises(ValueError, match="exclude each other"):
        gpu_blur.generate_set(tmp_path / "set", overwrite=True, resume=True)
    assert main(["generate", "--output", str(tmp_path / "set"), "--seed", "-1"]) == 2
    assert capsys.readouterr().err.splitlines()[-1] == (
        "gpu-blur: error: --seed -1: must lie in [0, 2**64)")


def write_sequence(folder, frames: int, seed: int) -> None:
    """A sequence of ``frames`` 24 x 32 noise PNGs as ``folder/seq/sharp/0000.png ...``."""
    import cv2
    import numpy as np

    sharp = folder / "seq" / "sharp"
    sharp.mkdir(parents=True)
    rng = np.random.default_rng(seed)
    for i in range(frames):
        cv2.imwrite(str(sharp / f"{i:04d}.png"), rng.integers(0, 256, (24, 32, 3), np.uint8))


def test_windows_sharing_a_centre_frame_encode_their_sharp_file_once(tmp_path, monkeypatch):
    from gpu_blur import file_writing
    from gpu_blur.image_reading import read_image

    write_sequence(tmp_path / "in", 12, seed=4)  # 9-frame windows: 4 first, so 4 centre frames
    sharp_encodes = []  # what each encode wrote
    encode = file_writing.encode_image
    monkeypatch.setattr(file_writing, "encode_image",
                        lambda *a: sharp_encodes.append(a[2]) or encode(*a))
    out = tmp_path / "out"
    assert main(["generate", "--input", str(tmp_path / "in"), "--output", str(out), "--scene",
                 "rsblur", "--backend", "numpy", "--samples-per-sequence", "16",
                 "--io-threads", "2", "--quiet"]) == 0
    sharp = sorted((out / "sharp").iterdir())
    sharp_encodes = [what for what in sharp_encodes if "sharp" in what]  # not the blurred
    assert len(sharp) == 16 and len({p.read_bytes() for p in sharp}) == len(sharp_encodes) == 4
    for path in sharp:  # each the file its pixels encode to
        assert path.read_bytes() == encode(read_image(path), 8)


def test_run_json_names_the_png_encoder_which_a_resume_does_not_check(tmp_path):
    from gpu_blur.png_codecs import encoder_name

    write_sequence(tmp_path / "in", 9, seed=5)
    out = tmp_path / "out"
    command = ["generate", "--input", str(tmp_path / "in"), "--output", str(out), "--scene",
               "rsblur", "--backend", "numpy", "--samples-per-sequence", "2", "--quiet"]
    assert main([*command, "--limit", "1"]) == 0
    run = json.loads((out / "run.json").read_text())
    assert run["png_encoder"] == encoder_name("fast")
    run["png_encoder"] = "another encoder"  # as a set whose first run had another library
    (out / "run.json").write_text(json.dumps(run))
    assert main([*command, "--resume"]) == 0
    assert len((out / "manifest.jsonl").read_text().splitlines()) == 2
