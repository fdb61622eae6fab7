"""What README.md promises a new user, beyond running its blocks (tests/docs/test_examples.py).

The torch extra installs what the transform runs on by default, and says so in Python words
when it is missing; data set items and the transform agree on layout; ``gpu-blur cameras``
fits 100 columns with each source once; ``plan --cost`` never prints a negative cost.
"""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from gpu_blur.analysis.stage_cost import (
    SWITCHES,
    StageCosts,
    cost_text,
    format_costs,
    median_interval,
)
from gpu_blur.cli import main
from gpu_blur.planning import plan

ROOT = Path(__file__).resolve().parents[2]

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib


def test_readme_is_short_and_its_links_lead_to_files_here():
    text = (ROOT / "README.md").read_text()
    assert len(text.splitlines()) <= 200
    targets = re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text)
    local = [t for t in targets if "://" not in t]
    assert "docs/scenes.md" in local and "docs/cli/index.md" in local
    missing = [t for t in local if not (ROOT / t).exists()]
    assert not missing, f"README.md links to {missing}, which are not in the repository"


def test_readme_carries_no_commit_hashes_issue_numbers_or_machine_paths():
    text = (ROOT / "README.md").read_text()
    hashes = [w for w in re.findall(r"\b[0-9a-f]{7,40}\b", text)
              if re.search(r"[a-f]", w) and re.search(r"\d", w)]
    assert not hashes
    assert not re.search(r"\bissues? \d+|#\d+\b", text, re.IGNORECASE)
    # an absolute folder of some machine: /<top>/ for these top folders, or a drive letter
    tops = "|".join(["work", "home", "root", "tmp"])
    assert not re.search(rf"(/({tops})/|[A-Z]:\\)", text)


def test_the_torch_extra_brings_the_transforms_default_backend():
    extras = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"][
        "optional-dependencies"]
    names = {re.split(r"[<>=;\[ ]", r, maxsplit=1)[0] for r in extras["torch"]}
    assert {"torch", "warp-lang"} <= names


def test_cameras_fit_100_columns_and_print_each_source_once(capsys):
    from gpu_blur.cameras import get_camera, preset_names

    assert main(["cameras"]) == 0
    out = capsys.readouterr().out
    assert max(len(line) for line in out.splitlines()) <= 100
    sources = {get_camera(n).source for n in preset_names()}
    flat = " ".join(out.split())
    for source in sources:
        assert flat.count(" ".join(source.split())) == 1, source
    rows = [line for line in out.splitlines() if line.startswith("rsblur-")]
    assert len(rows) == 19 and all(line.endswith("[3]") for line in rows)


@pytest.mark.parametrize("seconds, interval, text", [
    (0.0123, (0.010, 0.020), "12.3 ms"),
    (-0.0033, (-0.010, 0.002), "within noise (< 2.0 ms)"),
    (-0.00001, (-0.0001, 0.00002), "within noise (< 0.1 ms)"),
    (-0.0157, (-0.020, -0.010), "none (15.7 ms faster with it)"),
])
def test_a_cost_is_never_printed_negative(seconds, interval, text):
    assert cost_text(seconds, interval) == text


def test_the_median_interval_covers_at_least_90_percent():
    assert median_interval([5, 1, 3, 2, 4]) == (1, 5)  # 5 runs: their range, 94 %
    assert median_interval(range(9)) == (1, 7)  # the 2nd and 8th of 9: 96 %
    assert median_interval([2.0]) == (2.0, 2.0)


def test_the_cost_report_prints_no_negative_figure():
    p = plan("rsblur")
    switches = {name: (i % 2 == 0, -0.0033 if i % 2 else 0.004)
                for i, name in enumerate(SWITCHES)}
    intervals = {name: (-0.01, 0.002) if i % 2 else (0.001, 0.006)
                 for i, name in enumerate(SWITCHES)}
    intervals["every stage"] = (-0.004, 0.003)
    costs = StageCosts("numpy", "host CPU", (32, 48), 0.001, 0.030, 0.029, switches, {},
                       intervals)
    text = format_costs(costs, p)
    assert not re.search(r"-\d", text), text
    assert "within noise (< 2.0 ms)" in text and "4.0 ms" in text
    assert "the plan saves nothing measurable here" in text


def test_a_missing_backend_package_is_named_in_words_for_python_and_the_command():
    code = ("import sys; sys.modules['warp'] = None; import numpy, gpu_blur\n"
            "try:\n"
            "    gpu_blur.synthesize(numpy.zeros((8, 8, 3), numpy.uint8), backend='warp:cpu')\n"
            "except RuntimeError as e:\n"
            "    print(e)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == ("backend 'warp:cpu' needs NVIDIA Warp (package warp-lang), which is "
                           "not installed: pip install 'gpu_blur[warp]', or use the numpy "
                           "backend")


torch = pytest.importorskip("torch")


def test_data_set_items_feed_the_transform_as_the_loader_batches_them():
    from torch.utils.data import DataLoader

    from gpu_blur.torch import Photos, RealisticBlur

    data = Photos(samples_per_photo=2, crop=16, seed=1)
    index, photo = data[0]
    assert index == 0 and photo.shape == (16, 16, 3) and photo.dtype == np.uint8
    index, photos = next(iter(DataLoader(data, batch_size=2)))
    assert photos.shape == (2, 16, 16, 3) and index.tolist() == [0, 1]
    scene = {"blur": {"mode": "kernel", "kernel_size": [3, 5]}}
    blurred, sharp = RealisticBlur(scene, seed=1, backend="numpy")(photos, indices=index)
    assert blurred.shape == sharp.shape == (2, 16, 16, 3) and blurred.dtype == torch.float32
    first, _ = RealisticBlur(scene, seed=1, backend="numpy", channels_first=True)(
        photos.permute(0, 3, 1, 2), indices=index)
    assert torch.equal(first.permute(0, 2, 3, 1), blurred)  # one sample, either layout


def test_frame_stacks_from_a_data_set_read_as_channels_last():
    from gpu_blur.torch import RealisticBlur

    frames = torch.zeros((2, 3, 8, 8, 3), dtype=torch.uint8)  # B x F x H x W x 3
    blurred, _ = RealisticBlur({"blur": {"mode": "average", "frames": 3}}, backend="numpy")(
        frames)
    assert blurred.shape == (2, 8, 8, 3)


@pytest.mark.parametrize("shape, words", [
    ((2, 3, 8, 3), r"reads as channels-first and as channels-last; pass RealisticBlur\(\.\.\., "
                   r"channels_first=True\) or False"),
    ((2, 8, 8, 4), r"takes B x 3 x H x W or B x H x W x 3 .*got shape \(2, 8, 8, 4\)"),
])
def test_a_layout_the_shape_cannot_tell_is_refused_quoting_it(shape, words):
    from gpu_blur.torch import RealisticBlur

    with pytest.raises(ValueError, match=words):
        RealisticBlur({"blur": {"mode": "kernel"}}, backend="numpy")(
            torch.zeros(shape, dtype=torch.uint8))


def test_without_warp_the_default_backend_says_what_to_do_in_python_words(monkeypatch):
    from gpu_blur.torch import RealisticBlur

    monkeypatch.setitem(sys.modules, "warp", None)  # import warp fails, as when not installed
    with pytest.raises(RuntimeError) as e:
        RealisticBlur("rsblur")(torch.zeros((1, 9, 8, 8, 3), dtype=torch.uint8))
    message = str(e.value)
    assert "pip install 'gpu_blur[torch]'" in message and "backend='numpy'" in message
    assert "--backend" not in message
