"""``gpu-blur generate --format lmdb|webdataset``: the PNG set's bytes in BasicSR's paired
LMDB and in WebDataset tar shards, read back with the libraries their users read them with,
and resumed after a kill into what an uninterrupted run writes (issue 38)."""

import json
import os
import subprocess
import sys
import tarfile
import time
from pathlib import Path

import cv2
import lmdb
import numpy as np
import pytest
import webdataset as wds
from conftest import manifest_lines

from gpu_blur.cli import main
from gpu_blur.dataset import PATHS
from gpu_blur.set_formats import LMDB_FOLDERS, sample_key
from gpu_blur.testhooks import TEST_SLEEP_AFTER


def args(photos, out, *extra):
    folder, scene = photos
    return ["generate", "--input", str(folder), "--output", str(out), "--scene", str(scene),
            "--samples-per-photo", "4", "--quiet", *extra]


def without_files(line):
    """A manifest line without what names where its files are (the same in every format)."""
    return {k: v for k, v in line.items() if k not in PATHS and k != "key"}


def lmdb_contents(out):
    """{folder: {key: value}} of every LMDB of the set, read with the lmdb package."""
    found = {}
    for folder in LMDB_FOLDERS.values():
        if (out / folder / "data.mdb").is_file():
            with lmdb.open(str(out / folder), readonly=True, lock=False) as env, \
                    env.begin() as txn:
                found[folder] = dict(txn.cursor())
    return found


def shards(out):
    """{name: bytes} of every shard of the set."""
    return {p.name: p.read_bytes() for p in sorted(out.glob("shard-*.tar"))}


def temporaries(out):
    return sorted(p.name for p in out.rglob(".*.part*"))


def meta_infos(out):
    """{folder: bytes} of every LMDB environment's meta_info.txt."""
    return {p.parent.name: p.read_bytes() for p in sorted(out.glob("*.lmdb/meta_info.txt"))}


def assert_same_set(out, reference):
    """``out`` holds the set of ``reference``, an uninterrupted run: the manifest, and the shards
    or every environment and its meta_info.txt, byte for byte; no temporary file is left."""
    assert shards(reference) or lmdb_contents(reference), f"{reference} holds no set"
    assert (out / "manifest.jsonl").read_bytes() == (reference / "manifest.jsonl").read_bytes()
    assert shards(out) == shards(reference)
    assert lmdb_contents(out) == lmdb_contents(reference)
    assert meta_infos(out) == meta_infos(reference)
    assert temporaries(out) == []


@pytest.fixture(scope="module")
def made(shared_photos, tmp_path_factory):
    """``made(*options)``: the set of 8 samples (2 photos x 4) that ``generate`` with these
    options writes from ``shared_photos``, made once for the tests that read it (none writes)."""
    sets = {}

    def make(*options):
        if options not in sets:
            out = tmp_path_factory.mktemp("set") / "out"
            assert main(args(shared_photos, out, *options)) == 0
            sets[options] = out
        return sets[options]

    return make


@pytest.fixture(scope="module")
def png_set(made):
    """The PNG set with masks, from ``shared_photos``: what each format must hold."""
    return made("--save", "mask")


def test_an_lmdb_set_holds_the_png_sets_bytes_under_basicsrs_keys(made, png_set):
    out = made("--save", "mask", "--format", "lmdb")
    lines, expected = manifest_lines(out), manifest_lines(png_set)
    assert [without_files(x) for x in lines] == [without_files(x) for x in expected]
    stored = lmdb_contents(out)
    assert sorted(stored) == ["blur.lmdb", "mask.lmdb", "params.lmdb", "sharp.lmdb"]
    for line, png in zip(lines, expected, strict=True):
        key = line["key"]
        assert key == sample_key(line["index"], line["name"])
        assert key == f"{line['index']:06d}_{line['name']}"  # names a_0, b_3: kept as they are
        for kind, folder in LMDB_FOLDERS.items():
            if kind in png:
                assert line[kind] == f"{folder}/{key}"
                assert stored[folder][key.encode("ascii")] == (png_set / png[kind]).read_bytes()
    # meta_info.txt: "<key>.png (h,w,c) <compression level>" a line, in index order
    for folder in ("blur.lmdb", "sharp.lmdb", "mask.lmdb"):
        assert (out / folder / "meta_info.txt").read_text() == "".join(
            f"{x['key']}.png (24,32,3) 1\n" for x in lines)
    assert json.loads((out / "run.json").read_text())["format"] == "lmdb"
    assert not (out / "blur").exists() and temporaries(out) == []


@pytest.mark.parametrize("mode, bits, level", [("fast", 8, 1), ("fast", 16, 1), ("small", 8, 1),
                                               ("small", 16, 6), ("stored", 8, 0),
                                               ("stored", 16, 0)])
def test_meta_info_names_the_zlib_level_each_png_mode_writes(mode, bits, level):
    from gpu_blur.set_formats import png_level

    assert png_level(mode, bits) == level


def basicsr_pairs(lq_folder: str, gt_folder: str):
    """BasicSR's paired LMDB reading, its convention written out here (BasicSR itself does not
    install quickly: it builds CUDA extensions and pins torch).

    ``paired_paths_from_lmdb`` (basicsr/data/data_util.py): both folders end with ``.lmdb``,
    each meta_info.txt's keys are its lines up to the first dot, and the two key sets must
    be equal; ``LmdbBackend.get`` (basicsr/utils/file_client.py) opens each environment
    read-only without a lock or readahead and gets ``key.encode('ascii')``; ``imfrombytes``
    (basicsr/utils/img_util.py) decodes with IMREAD_COLOR, as float32 / 255 (BGR).
    """
    if not (lq_folder.endswith(".lmdb") and gt_folder.endswith(".lmdb")):
        raise ValueError("lq folder and gt folder should both in lmdb formats")
    keys = []
    for folder in (lq_folder, gt_folder):
        with open(os.path.join(folder, "meta_info.txt")) as fin:
            keys.append([line.split(".")[0] for line in fin])
    if set(keys[0]) != set(keys[1]):
        raise ValueError("Keys in lq_folder and gt_folder are different.")
    envs = [lmdb.open(f, readonly=True, lock=False, readahead=False)
            for f in (lq_folder, gt_folder)]
    try:
        for key in sorted(keys[0]):
            images = []
            for env in envs:
                with env.begin(write=False) as txn:
                    data = txn.get(key.encode("ascii"))
                img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
                images.append(img.astype(np.float32) / 255.0)
            yield key, images[0], images[1]
    finally:
        for env in envs:
            env.close()


def test_a_basicsr_paired_lmdb_reader_sees_every_pair(made, png_set):
    out = made("--format", "lmdb")
    pairs = list(basicsr_pairs(str(out / "blur.lmdb"), str(out / "sharp.lmdb")))
    lines = manifest_lines(png_set)
    assert [key for key, _, _ in pairs] == [sample_key(x["index"], x["name"]) for x in lines]
    for (_, lq, gt), line in zip(pairs, lines, strict=True):
        for image, kind in ((lq, "blurred"), (gt, "sharp")):
            png = cv2.imread(str(png_set / line[kind]), cv2.IMREAD_COLOR)
            assert np.array_equal(image, png.astype(np.float32) / 255.0)


def test_a_webdataset_set_reads_back_with_webdataset(tmp_path, shared_photos, png_set):
    out = tmp_path / "wds"
    assert main(args(shared_photos, out, "--save", "mask", "--format", "webdataset",
                     "--shard-size", "3")) == 0
    assert sorted(shards(out)) == ["shard-000000.tar", "shard-000001.tar", "shard-000002.tar"]
    urls = str(out / "shard-{000000..000002}.tar")
    samples = list(wds.WebDataset(urls, shardshuffle=False))
    lines, expected = manifest_lines(out), manifest_lines(png_set)
    assert [s["__key__"] for s in samples] == [x["key"] for x in lines]
    for sample, line, png in zip(samples, lines, expected, strict=True):
        assert sorted(k for k in sample if not k.startswith("__")) == [
            "blur.png", "json", "mask.png", "params.npz", "sharp.png"]
        for kind, ext in (("blurred", "blur.png"), ("sharp", "sharp.png"),
                          ("mask", "mask.png"), ("arrays", "params.npz")):
            assert sample[ext] == (png_set / png[kind]).read_bytes()
            assert line[kind] == f"shard-{line['index'] // 3:06d}.tar/{line['key']}.{ext}"
        assert json.loads(sample["json"]) == {k: v for k, v in without_files(png).items()
                                              if k != "bytes"}
    # decoded as WebDataset users decode them: the PNG set's pixels
    decoded = wds.WebDataset(urls, shardshuffle=False).decode("rgb8").to_tuple(
        "blur.png", "sharp.png", "json")
    for (blurred, sharp, record), png in zip(decoded, expected, strict=True):
        for image, kind in ((blurred, "blurred"), (sharp, "sharp")):
            codes = cv2.cvtColor(cv2.imread(str(png_set / png[kind])), cv2.COLOR_BGR2RGB)
            assert np.array_equal(image, codes)
        assert record["params"] == png["params"]


def test_shards_are_the_same_bytes_in_any_run_with_fixed_member_metadata(tmp_path, photos):
    first, second = tmp_path / "first", tmp_path / "second"
    assert main(args(photos, first, "--format", "webdataset", "--shard-size", "5")) == 0
    assert main(args(photos, second, "--format", "webdataset", "--shard-size", "5",
                     "--io-threads", "1")) == 0
    assert shards(first) == shards(second) and len(shards(first)) == 2
    with tarfile.open(first / "shard-000001.tar") as tar:
        members = tar.getmembers()
    keys = [x["key"] for x in manifest_lines(first)[5:]]
    assert [m.name for m in members] == [f"{k}.{ext}" for k in keys
                                         for ext in ("blur.png", "sharp.png", "params.npz",
                                                     "json")]
    assert {(m.mtime, m.mode, m.uid, m.gid, m.uname, m.gname, m.type) for m in members} == {
        (0, 0o444, 0, 0, "", "", tarfile.REGTYPE)}


def test_keys_are_ascii_without_dots_whatever_the_name(tmp_path, photos):
    folder, _ = photos
    (folder / "b.png").rename(folder / "shot 1.v2 é.png")  # dots, a space, non-ASCII
    out = tmp_path / "wds"
    assert main(args(photos, out, "--format", "webdataset")) == 0
    lines = manifest_lines(out)
    assert lines[4]["name"].startswith("shot 1.v2 é")
    assert lines[4]["key"] == "000004_shot_1_v2__" + lines[4]["name"][len("shot 1.v2 é"):]
    samples = list(wds.WebDataset(str(out / "shard-000000.tar"), shardshuffle=False))
    assert [s["__key__"] for s in samples] == [x["key"] for x in lines]  # 8 whole samples
    assert all("blur.png" in s and "sharp.png" in s for s in samples)


def killed_after_sample_2(tmp_path, command, out):
    """Run ``command`` in a process that sleeps once sample 2 is recorded; SIGKILL it there."""
    log = (tmp_path / "killed.log").open("w")
    env = {**os.environ, TEST_SLEEP_AFTER: "2"}
    run = subprocess.Popen([sys.executable, "-m", "gpu_blur.cli", *command], env=env,
                           stdout=log, stderr=subprocess.STDOUT)
    try:
        deadline = time.monotonic() + 60
        manifest = out / "manifest.jsonl"
        while (manifest.read_text().count("\n") if manifest.exists() else 0) < 3:
            assert run.poll() is None, (tmp_path / "killed.log").read_text()
            assert time.monotonic() < deadline, "the run never reached sample 2"
            time.sleep(0.05)
        assert run.poll() is None
    finally:
        run.kill()
        run.wait()
        log.close()
    return run.pid


def test_a_killed_webdataset_run_resumes_to_the_shards_an_uninterrupted_run_writes(tmp_path,
                                                                                  photos):
    options = ("--format", "webdataset", "--shard-size", "2", "--save", "mask")
    reference = tmp_path / "reference"
    assert main(args(photos, reference, *options)) == 0
    out = tmp_path / "out"
    pid = killed_after_sample_2(tmp_path, args(photos, out, *options), out)
    # shard 0 (samples 0, 1) is finished; shard 1 holds sample 2 under its temporary name only
    assert sorted(shards(out)) == ["shard-000000.tar"]
    assert shards(out)["shard-000000.tar"] == shards(reference)["shard-000000.tar"]
    assert temporaries(out) == [f".shard-000001.tar.{pid}.part.tar"]
    assert [x["index"] for x in manifest_lines(out)] == [0, 1, 2]
    finished = (out / "shard-000000.tar").stat()

    assert main(args(photos, out, *options, "--resume")) == 0
    assert (out / "shard-000000.tar").stat().st_ino == finished.st_ino  # untouched
    assert_same_set(out, reference)


def test_a_killed_lmdb_run_resumes_to_the_samples_an_uninterrupted_run_writes(tmp_path,
                                                                             shared_photos,
                                                                             made):
    options = ("--format", "lmdb", "--save", "mask")
    reference = made(*options)
    out = tmp_path / "out"
    killed_after_sample_2(tmp_path, args(shared_photos, out, *options), out)
    lines = manifest_lines(out)
    assert [x["index"] for x in lines] == [0, 1, 2]
    # a kill at a worse moment: sample 3's values put in two environments, without its line
    key = sample_key(3, manifest_lines(reference)[3]["name"]).encode("ascii")
    for folder in ("blur.lmdb", "sharp.lmdb"):
        with lmdb.open(str(out / folder)) as env, env.begin(write=True) as txn:
            txn.put(key, b"\x89PNG half an image")

    assert main(args(shared_photos, out, *options, "--resume")) == 0
    assert sorted(meta_infos(out)) == ["blur.lmdb", "mask.lmdb", "sharp.lmdb"]
    assert_same_set(out, reference)


@pytest.mark.parametrize("format", ["lmdb", "webdataset"])
def test_resume_remakes_failed_samples_into_finished_shards_and_environments(tmp_path, photos,
                                                                             format):
    # b's samples (4 to 7) fail; with 3 samples a shard, shard 1 (3, 4, 5) is finished
    # holding sample 3 alone, and is rewritten with 4 and 5 once b.png is fixed
    options = ("--format", format, *(("--shard-size", "3") if format == "webdataset" else ()))
    folder, _ = photos
    good = (folder / "b.png").read_bytes()
    (folder / "b.png").write_bytes(good[:50])
    out = tmp_path / "out"
    assert main(args(photos, out, *options)) == 1
    if format == "webdataset":
        with tarfile.open(out / "shard-000001.tar") as tar:
            assert {m.name.split(".")[0] for m in tar} == {"000003_a_3"}
    (folder / "b.png").write_bytes(good)
    assert main(args(photos, out, *options, "--resume")) == 0
    reference = tmp_path / "reference"
    assert main(args(photos, reference, *options)) == 0
    assert_same_set(out, reference)


@pytest.mark.parametrize("options, message", [
    (["--format", "zip"], "--format zip: unknown; choose one of png, lmdb, webdataset"),
    (["--shard-size", "4"], "--shard-size 4: only --format webdataset writes shards (this "
                            "run: --format png); drop --shard-size or pass --format webdataset"),
    (["--format", "webdataset", "--shard-size", "0"], "--shard-size 0: samples per shard, "
                                                      "must be >= 1"),
    (["--format", "lmdb", "tiff"], "--format lmdb: the scene's output.bits = 0 writes float32 "
                                   "TIFF, but BasicSR's LMDB holds PNG images"),
])
def test_a_bad_format_option_is_refused_before_anything_is_written(tmp_path, photos, capsys,
                                                                   options, message):
    if "tiff" in options:
        options = options[:-1]
        photos[1].write_text("[blur]\nsteps = 3\n[output]\nbits = 0\n")
    out = tmp_path / "out"
    assert main(args(photos, out, *options)) == 2
    (error,) = [x for x in capsys.readouterr().err.splitlines() if "error" in x]
    assert error.startswith(f"gpu-blur: error: {message}")
    assert not out.exists()


def test_a_float_tiff_set_goes_into_shards_as_tiff(tmp_path, photos):
    photos[1].write_text("[blur]\nsteps = 3\n[output]\nbits = 0\n")
    png, out = tmp_path / "png", tmp_path / "wds"
    assert main(args(photos, png, "--limit", "1")) == 0
    assert main(args(photos, out, "--limit", "1", "--format", "webdataset")) == 0
    (sample,) = wds.WebDataset(str(out / "shard-000000.tar"), shardshuffle=False)
    line = manifest_lines(png)[0]
    assert sample["blur.tiff"] == (png / line["blurred"]).read_bytes()


def test_resume_refuses_another_format_and_overwrite_replaces_any(tmp_path, photos, capsys):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "2")) == 0
    capsys.readouterr()
    assert main(args(photos, out, "--limit", "2", "--format", "lmdb", "--resume")) == 2
    assert "made with another --format: format = None (this run: 'lmdb')" in (
        capsys.readouterr().err)
    assert main(args(photos, out, "--limit", "2", "--format", "webdataset",
                     "--overwrite")) == 0
    assert sorted(p.name for p in out.iterdir()) == ["manifest.jsonl", "run.json",
                                                     "shard-000000.tar"]
    assert main(args(photos, out, "--limit", "2", "--format", "lmdb", "--overwrite")) == 0
    assert sorted(p.name for p in out.iterdir()) == ["blur.lmdb", "manifest.jsonl",
                                                     "params.lmdb", "run.json", "sharp.lmdb"]
    assert main(args(photos, out, "--limit", "2", "--overwrite")) == 0
    assert sorted(p.name for p in out.iterdir()) == ["blur", "manifest.jsonl", "params",
                                                     "run.json", "sharp"]


def test_a_file_in_an_lmdb_folder_that_is_not_the_sets_is_refused(tmp_path, photos, capsys):
    out = tmp_path / "out"
    assert main(args(photos, out, "--limit", "1", "--format", "lmdb")) == 0
    (out / "blur.lmdb" / "notes.txt").write_text("mine")
    capsys.readouterr()
    assert main(args(photos, out, "--limit", "1", "--format", "lmdb", "--overwrite")) == 2
    assert f"{out / 'blur.lmdb' / 'notes.txt'}: not a file gpu-blur wrote" in (
        capsys.readouterr().err)
    assert (out / "blur.lmdb" / "notes.txt").read_text() == "mine"
    assert Path(out / "blur.lmdb" / "data.mdb").is_file()


def test_a_stopped_run_drops_its_unfinished_shard_and_resumes(tmp_path, photos):
    import gpu_blur
    from gpu_blur.generation import SetInterrupted

    folder, scene = photos
    options = {"input": folder, "scene": scene, "samples_per_photo": 4,
               "format": "webdataset", "shard_size": 3}

    def stop(done, total):
        if done == 5:
            raise KeyboardInterrupt

    out = tmp_path / "out"
    with pytest.raises(SetInterrupted):
        gpu_blur.generate_set(out, progress=stop, io_threads=1, **options)
    # shard 0 (0 to 2) finished; shard 1 (3 to 5) was missing sample 5: dropped, not renamed
    assert sorted(shards(out)) == ["shard-000000.tar"] and temporaries(out) == []
    assert [x["index"] for x in manifest_lines(out)] == [0, 1, 2, 3, 4]
    report = gpu_blur.generate_set(out, resume=True, **options)
    assert (report.skipped, report.made) == (3, 5)  # 3 and 4 were in the dropped shard
    reference = tmp_path / "reference"
    gpu_blur.generate_set(reference, **options)
    assert_same_set(out, reference)


@pytest.mark.slow
@pytest.mark.parametrize("format", ["lmdb", "webdataset"])
def test_devices_write_the_serial_runs_samples(tmp_path, shared_photos, made, format):
    # worker processes hand samples back in any order; shards and keys go in in sample order
    options = ("--format", format, *(("--shard-size", "3") if format == "webdataset" else ()))
    spread = tmp_path / "spread"
    assert main(args(shared_photos, spread, *options, "--devices", "numpy,numpy")) == 0
    assert_same_set(spread, made(*options))


def test_meta_info_gives_the_compression_level_of_the_png_mode(tmp_path, photos):
    # output.png = 'small': OpenCV's libpng at level 1 for 8 bits, 6 for 16 (the masks)
    photos[1].write_text('[blur]\nsteps = 3\n[output]\npng = "small"\n')
    png, out = tmp_path / "png", tmp_path / "lmdb"
    assert main(args(photos, png, "--limit", "2", "--save", "mask")) == 0
    assert main(args(photos, out, "--limit", "2", "--save", "mask", "--format", "lmdb")) == 0
    lines, stored = manifest_lines(png), lmdb_contents(out)
    for line in lines:
        key = sample_key(line["index"], line["name"]).encode("ascii")
        assert stored["mask.lmdb"][key] == (png / line["mask"]).read_bytes()
    keys = [sample_key(x["index"], x["name"]) for x in lines]
    for folder, level in (("blur.lmdb", 1), ("sharp.lmdb", 1), ("mask.lmdb", 6)):
        assert (out / folder / "meta_info.txt").read_text() == "".join(
            f"{k}.png (24,32,3) {level}\n" for k in keys)


@pytest.mark.parametrize("format", ["lmdb", "webdataset"])
def test_a_larger_limit_grows_the_last_shard_and_the_environments(tmp_path, shared_photos,
                                                                   made, format):
    options = ("--format", format, *(("--shard-size", "3") if format == "webdataset" else ()))
    out = tmp_path / "out"
    assert main(args(shared_photos, out, *options, "--limit", "4")) == 0  # shard 1: sample 3
    assert main(args(shared_photos, out, *options, "--resume")) == 0
    assert_same_set(out, made(*options))
