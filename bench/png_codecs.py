"""PNG decoders and encoders on one core: ms an image, MB an image, and whether pixels survive.

Images (RGB, 8 and 16 bits): ``noisy``, 1920 x 1200, the built-in photo upscaled (cubic) plus
Gaussian noise of std 0.01 (seed 0) before quantisation, as a synthesised output has noise;
``smooth``, the same without noise (what bench/generate_gpu.py feeds generate as inputs);
``coffee``, the built-in photo itself (600 x 400). The 16-bit images are the same float
values quantised to 65535 codes.

Encoders: gpu_blur's own (every ``output.png`` mode, gpu_blur.png_codecs); OpenCV's
libpng at several compression levels, strategies and filters; libspng (``pyspng-seunglab``'s
encode, imagecodecs' spng_encode); imagecodecs' libpng; fpng (``fpng``, ``fpng-py``: 8-bit
RGB only); Pillow (8-bit only); and gpu_blur.png_codecs' numpy filter with a zlib stream from
Python's zlib, zlib-ng, ISA-L (``isal``) or libdeflate (imagecodecs). Each encoded file is
decoded back by OpenCV: ``same`` says whether every code came back.

Decoders, back to an RGB array: gpu_blur's read_image (from a file in the page cache, every
check included), OpenCV (imdecode and the BGR -> RGB swap), libspng (``pyspng``: 16-bit RGB
comes as RGBA, its alpha dropped; ``pyspng-seunglab``; imagecodecs' spng_decode, 8-bit
only), imagecodecs' libpng, Pillow (16-bit RGB comes back as 8 bits: not the same), fpng
(its own files only). Each decodes every file once for ``same``, and is timed on the files
of :data:`TIMED_FILES`. A library that is not installed is left out (listed in
``missing``). pyspng-seunglab installs a module named ``pyspng`` too, and the two register
the same pybind11 types, so it runs in a child process on the same core (encoding, and
decoding its own files and OpenCV's default and level-6 ones): give its folder with
``--seunglab DIR`` (pip install --target DIR pyspng-seunglab).

Times: each codec called once to warm up, then ``--runs`` rounds that call every codec of
the image in turn (load from other processes spreads over all of them), median and fastest;
OpenCV on one thread, the process pinned to one core (Linux).

    PYTHONPATH=$PWD python bench/png_codecs.py --json bench/results/png_codecs_<cpu>.json
"""

from __future__ import annotations

import argparse
import importlib.metadata
import importlib.util
import io
import json
import math
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
import zlib
from pathlib import Path

import cv2
import numpy as np

import gpu_blur
from gpu_blur import png_codecs
from gpu_blur.analysis.bench.host import cpu_name, load_average, source_commit
from gpu_blur.discovery import default_photo
from gpu_blur.image_reading import read_image
from gpu_blur.png_codecs import PNG_MODES, encode_png, filtered_rows, png_file

H, W = 1200, 1920
MISSING: dict[str, str] = {}


def images() -> dict[str, tuple[str, np.ndarray]]:
    """name -> (what it is, H x W x 3 float64 RGB in [0, 1])."""
    photo = cv2.imread(str(default_photo()))[:, :, ::-1] / 255.0
    smooth = np.clip(cv2.resize(photo, (W, H), interpolation=cv2.INTER_CUBIC), 0, 1)
    noise = np.random.default_rng(0).normal(0.0, 0.01, smooth.shape)
    return {
        "noisy": (f"{W} x {H}: the built-in photo upscaled (cubic) + Gaussian noise of std "
                  "0.01, seed 0", np.clip(smooth + noise, 0, 1)),
        "smooth": (f"{W} x {H}: the built-in photo upscaled (cubic), no noise", smooth),
        "coffee": ("600 x 400: the built-in photo gpu_blur/data/coffee.png", photo),
    }


def codes(values: np.ndarray, bits: int) -> np.ndarray:
    top = 2**bits - 1
    return np.rint(values * top).astype(np.uint8 if bits == 8 else np.uint16)


def optional(module: str, distribution: str | None = None):
    """The module, or None (noted in MISSING) when it is not installed."""
    try:
        return __import__(module, fromlist=["_"])
    except ImportError as e:
        MISSING[distribution or module] = str(e)
        return None


def seunglab(folder: str):
    """pyspng-seunglab's module, loaded from ``folder`` under another name."""
    sys.path.insert(0, folder)  # its C extension is the top-level module _pyspng_c
    try:
        spec = importlib.util.spec_from_file_location("pyspng_seunglab",
                                                      Path(folder) / "pyspng" / "__init__.py")
        module = importlib.util.module_from_spec(spec)
        spec.loader.exec_module(module)
        return module
    finally:
        sys.path.remove(folder)


def version(distribution: str) -> str | None:
    try:
        return importlib.metadata.version(distribution)
    except importlib.metadata.PackageNotFoundError:
        return None


def bgr(rgb: np.ndarray) -> np.ndarray:
    return np.ascontiguousarray(rgb[:, :, ::-1])


def encoders(args) -> dict[str, dict]:
    """name -> {"codec", "setting", "fn": codes -> bytes, "bits": (8, 16) it handles}.

    In the child of ``--seunglab``: OpenCV's default and level 6, and pyspng-seunglab's.
    """
    found: dict[str, dict] = {}

    def add(codec: str, setting: str, fn, bits=(8, 16)):
        found[f"{codec}: {setting}"] = {"codec": codec, "setting": setting, "fn": fn,
                                        "bits": bits}

    def opencv(params):
        return lambda c: cv2.imencode(".png", bgr(c), params)[1].tobytes()

    S = {"default": cv2.IMWRITE_PNG_STRATEGY_DEFAULT, "rle": cv2.IMWRITE_PNG_STRATEGY_RLE,
         "huffman": cv2.IMWRITE_PNG_STRATEGY_HUFFMAN_ONLY,
         "filtered": cv2.IMWRITE_PNG_STRATEGY_FILTERED, "fixed": cv2.IMWRITE_PNG_STRATEGY_FIXED}
    F = {"sub": cv2.IMWRITE_PNG_FILTER_SUB, "none": cv2.IMWRITE_PNG_FILTER_NONE,
         "up": cv2.IMWRITE_PNG_FILTER_UP, "paeth": cv2.IMWRITE_PNG_FILTER_PAETH,
         "all": cv2.IMWRITE_PNG_ALL_FILTERS}
    add("opencv", "no parameters (its default: level 1, RLE, Sub)", opencv([]))
    if not args.child:
        for mode in PNG_MODES:
            add(f"gpu_blur {gpu_blur.__version__}", f"output.png = {mode}",
                lambda c, mode=mode: encode_png(c, mode))
    for level in (0, 1, 3, 6, 9) if not args.child else (6,):
        add("opencv", f"level {level}, default strategy, libpng's filter per row",
            opencv([cv2.IMWRITE_PNG_COMPRESSION, level,
                    cv2.IMWRITE_PNG_STRATEGY, S["default"]]))
    if args.child:
        spng2 = seunglab(args.seunglab)
        name = f"pyspng-seunglab {spng2.__version__}"
        for level in (1, 6):
            add(name, f"level {level}",
                lambda c, level=level: spng2.encode(c, compress_level=level))
        return found
    for name in ("rle", "huffman", "filtered", "fixed"):
        add("opencv", f"level 1, strategy {name}, libpng's filter per row",
            opencv([cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, S[name]]))
    for name in ("none", "up", "paeth", "all"):
        add("opencv", f"level 1, RLE, filter {name}",
            opencv([cv2.IMWRITE_PNG_COMPRESSION, 1, cv2.IMWRITE_PNG_STRATEGY, S["rle"],
                    cv2.IMWRITE_PNG_FILTER, F[name]]))

    # gpu_blur.png_codecs' numpy filter + a zlib stream
    def numpy_zlib(kind, level, strategy=zlib.Z_DEFAULT_STRATEGY):
        def encode(c):
            squeeze = zlib.compressobj(level, zlib.DEFLATED, 15, 9, strategy)
            return png_file(c, squeeze.compress(filtered_rows(c, kind)) + squeeze.flush())
        return encode

    zname = f"numpy filter + Python zlib {zlib.ZLIB_RUNTIME_VERSION}"
    for kind in ("sub", "up", "none"):
        add(zname, f"{kind}, level 1, RLE", numpy_zlib(kind, 1, zlib.Z_RLE))
    add(zname, "sub, level 1, huffman only", numpy_zlib("sub", 1, zlib.Z_HUFFMAN_ONLY))
    add(zname, "sub, level 1", numpy_zlib("sub", 1))
    add(zname, "paeth, level 1, RLE", numpy_zlib("paeth", 1, zlib.Z_RLE))
    add(zname, "sub, level 6", numpy_zlib("sub", 6))

    zng = optional("zlib_ng.zlib_ng", "zlib-ng")
    if zng:
        name = f"numpy filter + zlib-ng {zng.ZLIBNG_VERSION}"

        def numpy_zng(kind, level, strategy=zng.Z_DEFAULT_STRATEGY):
            def encode(c):
                squeeze = zng.compressobj(level, zng.DEFLATED, 15, 9, strategy)
                return png_file(c, squeeze.compress(filtered_rows(c, kind)) + squeeze.flush())
            return encode

        for level in (1, 2, 6, 9):
            add(name, f"sub, level {level}", numpy_zng("sub", level))
        add(name, "up, level 1", numpy_zng("up", 1))
        add(name, "paeth, level 1", numpy_zng("paeth", 1))
        add(name, "sub, level 1, RLE", numpy_zng("sub", 1, zng.Z_RLE))
        add(name, "sub, level 1, huffman only", numpy_zng("sub", 1, zng.Z_HUFFMAN_ONLY))
    isal = optional("isal.isal_zlib", "isal")
    if isal:
        name = f"numpy filter + ISA-L (isal {version('isal')})"
        for level in (0, 1, 2, 3):
            add(name, f"sub, level {level}",
                lambda c, level=level: png_file(c, isal.compress(filtered_rows(c, "sub"), level)))
    ic = optional("imagecodecs")
    if ic:
        libdeflate = f"numpy filter + libdeflate {ic.deflate_version()}"
        for level in (1, 6, 12):
            add(libdeflate, f"sub, level {level}",
                lambda c, level=level: png_file(c, ic.deflate_encode(filtered_rows(c, "sub"),
                                                                     level)))
        name = f"imagecodecs {ic.__version__} libpng {ic.png_version()}"
        add(name, "level 1, RLE, Sub (its fast setting)",
            lambda c: ic.png_encode(c, level=1, strategy=3, filter=16))
        add(name, "level 6", lambda c: ic.png_encode(c, level=6))
        name = f"imagecodecs {ic.__version__} libspng {ic.spng_version()}"
        add(name, "level 1", lambda c: ic.spng_encode(c, level=1))
        add(name, "default level", lambda c: ic.spng_encode(c))
    fpng = optional("fpng")
    if fpng:
        add(f"fpng {version('fpng')}", "default",
            lambda c: fpng.fpng_ext.encode_ndarray(np.ascontiguousarray(c)), bits=(8,))
    fpng_py = optional("fpng_py", "fpng-py")
    if fpng_py:
        def fpng_py_encode(c, flags=0):
            h, w, ch = c.shape
            return bytes(fpng_py.fpng_encode_image_to_memory(np.ascontiguousarray(c).tobytes(),
                                                            w, h, ch, flags))
        add(f"fpng-py {version('fpng-py')}", "default", fpng_py_encode, bits=(8,))
        add(f"fpng-py {version('fpng-py')}", "slower",
            lambda c: fpng_py_encode(c, fpng_py.CompressionFlags.FPNG_ENCODE_SLOWER), bits=(8,))
    pil = optional("PIL.Image", "pillow")
    if pil:
        def pillow(level):
            def encode(c):
                out = io.BytesIO()
                pil.fromarray(c).save(out, "PNG", compress_level=level)
                return out.getvalue()
            return encode
        for level in (1, 6):
            add(f"Pillow {version('pillow')}", f"compress_level {level}", pillow(level),
                bits=(8,))  # Pillow has no 16-bit RGB mode
    return found


def decoders(args) -> dict[str, dict]:
    """name -> {"fn": bytes -> RGB array or None, "bits": (8, 16) it is tried on}."""
    found = {f"opencv {cv2.__version__} (libpng)": {
        "fn": lambda d: cv2.cvtColor(cv2.imdecode(np.frombuffer(d, np.uint8),
                                                  cv2.IMREAD_UNCHANGED), cv2.COLOR_BGR2RGB),
        "bits": (8, 16)}}
    if not args.child:
        found[f"gpu_blur {gpu_blur.__version__} read_image"] = {"fn": read_file, "bits": (8, 16)}
    if args.child:
        spng2 = seunglab(args.seunglab)
        found[f"pyspng-seunglab {spng2.__version__} (libspng)"] = {
            "fn": lambda d: rgb_of_spng(spng2.load(d)), "bits": (8, 16)}
        return found
    spng = optional("pyspng")
    if spng:
        found[f"pyspng {version('pyspng')} (libspng)"] = {
            "fn": lambda d: rgb_of_spng(spng.load(d)), "bits": (8, 16)}
    ic = optional("imagecodecs")
    if ic:
        found[f"imagecodecs libpng {ic.png_version()}"] = {"fn": ic.png_decode, "bits": (8, 16)}
        found[f"imagecodecs libspng {ic.spng_version()}"] = {"fn": ic.spng_decode, "bits": (8,)}
    pil = optional("PIL.Image", "pillow")
    if pil:
        found[f"Pillow {version('pillow')}"] = {
            "fn": lambda d: np.asarray(pil.open(io.BytesIO(d))), "bits": (8, 16)}
    fpng_py = optional("fpng_py", "fpng-py")
    if fpng_py:
        def fpng_decode(data):
            if not _is_fpng(data):
                return None
            pixels, width, height, _ = fpng_py.fpng_decode_from_memory(data, 3)
            return np.frombuffer(pixels, np.uint8).reshape(height, width, 3)
        found[f"fpng-py {version('fpng-py')} (fpng's own files)"] = {"fn": fpng_decode,
                                                                    "bits": (8,)}
    return found


FOLDER = Path(tempfile.mkdtemp(prefix="png_codecs_"))


WRITTEN: dict[str, bytes] = {}


def read_file(data: bytes) -> np.ndarray:
    """gpu_blur's read_image of ``data`` written to a file (once: then in the page cache)."""
    path = FOLDER / "image.png"
    if WRITTEN.get("data") is not data:
        path.write_bytes(data)
        WRITTEN["data"] = data
    return read_image(path)


def rgb_of_spng(image: np.ndarray) -> np.ndarray:
    """pyspng's array of an RGB file: 16-bit ones come as RGBA, whose alpha is dropped."""
    return np.ascontiguousarray(image[:, :, :3]) if image.shape[2] == 4 else image


def _is_fpng(data: bytes) -> bool:
    return b"fdEC" in data[:64]  # fpng marks its files with a private chunk


def interleaved_ms(calls: dict, runs: int) -> dict[str, tuple[float, float, object]]:
    """name -> (median ms, fastest ms, result) of each call, timed in turns.

    Each call runs once (warm-up, its result kept), then ``runs`` rounds time every call once
    in turn, so that a burst of load from another process spreads over all of them rather
    than landing on a few; a call of more than a second is timed in 3 rounds only. A call
    that raises is left out (its error is its result).
    """
    results, times = {}, {}
    for name, fn in calls.items():
        try:
            start = time.perf_counter()
            results[name] = fn()
            times[name] = [time.perf_counter() - start]  # dropped: the warm-up
        except Exception as error:  # a codec that refuses: noted, not fatal
            results[name] = error
    for round_ in range(runs):
        for name, fn in calls.items():
            if isinstance(results[name], Exception) or (round_ >= 3 and times[name][0] > 1):
                continue
            start = time.perf_counter()
            fn()
            times[name].append(time.perf_counter() - start)
    return {name: ((1e3 * statistics.median(times[name][1:]), 1e3 * min(times[name][1:]),
                    results[name]) if name in times else (None, None, results[name]))
            for name in calls}


def same(decoded, source: np.ndarray) -> bool:
    return (isinstance(decoded, np.ndarray) and decoded.shape == source.shape
            and decoded.dtype == source.dtype and bool(np.array_equal(decoded, source)))


def library_versions() -> dict[str, str]:
    found = {d: version(d) for d in ("opencv-python-headless", "numpy", "pyspng",
                                     "pyspng-seunglab", "imagecodecs", "zlib-ng", "isal",
                                     "deflate", "fpng", "fpng-py", "pillow") if version(d)}
    return {**found, "python zlib": zlib.ZLIB_RUNTIME_VERSION}


def cpu_tag(name: str) -> str:
    name = re.sub(r"\((R|TM)\)|\bCPU\b|\bProcessor\b|@.*$", " ", name, flags=re.I)
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-") or "cpu"


def machine() -> dict:
    info = {"cpu": cpu_name(), "cores": os.cpu_count(), "os": platform.platform(),
            "python": platform.python_version()}
    try:
        text = Path("/proc/cpuinfo").read_text()
        for key, label in (("cpu family", "family"), ("model", "model"),
                           ("flags", "flags")):
            m = re.search(rf"^{key}\s*:\s*(.*)$", text, re.M)
            if m:
                info[label] = (m.group(1) if key != "flags" else
                               " ".join(f for f in m.group(1).split()
                                        if f in ("avx2", "avx512f", "avx512bw", "vpclmulqdq",
                                                 "pclmulqdq", "sse4_2", "bmi2")))
    except OSError:
        pass
    return info


#: Files each decoder is timed on (a prefix of the encoder's name); every decoder decodes
#: every file once for ``same``.
TIMED_FILES = ("opencv: no parameters", "opencv: level 6,", "gpu_blur", "fpng-py",
               "Pillow 13.0.0: compress_level 6", "pyspng-seunglab")


def measure(args, enc: dict, dec: dict, all_images: dict) -> tuple[list, list]:
    """Every encoder on every image and bit depth, then every decoder on each file made."""
    say = sys.stderr if args.child else sys.stdout
    encoded_rows, decoded_rows = [], []
    for image_name in args.images.split(","):
        for bits in (8, 16):
            source = codes(all_images[image_name][1], bits)
            here = {name: e for name, e in enc.items() if bits in e["bits"]}
            timed = interleaved_ms({name: (lambda e=e, s=source: e["fn"](s))
                                    for name, e in here.items()}, args.runs)
            files = {}
            for name, (ms, ms_min, data) in timed.items():
                row = {"image": image_name, "bits": bits, "encoder": name}
                if isinstance(data, Exception):
                    encoded_rows.append({**row, "error": f"{type(data).__name__}: {data}"})
                    continue
                back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
                ok = back is not None and same(cv2.cvtColor(back, cv2.COLOR_BGR2RGB)
                                               if back.ndim == 3 else back, source)
                files[name] = data
                encoded_rows.append({**row, "codec": here[name]["codec"],
                                     "setting": here[name]["setting"], "ms": round(ms, 2),
                                     "ms_min": round(ms_min, 2),
                                     "mb": round(len(data) / 1e6, 3), "same": ok})
                print(f"encode {image_name:6} {bits:2}-bit {name:80} {ms:8.1f} ms "
                      f"{len(data) / 1e6:7.3f} MB same={ok}", file=say, flush=True)
            decoders_here = {name: d for name, d in dec.items() if bits in d["bits"]}
            for file_name, data in files.items():
                calls = {name: (lambda d=d, b=data: d["fn"](b))
                         for name, d in decoders_here.items()}
                if file_name.startswith(TIMED_FILES):
                    timed = interleaved_ms(calls, args.runs)
                else:  # decoded once, for same
                    timed = {}
                    for name, call in calls.items():
                        try:
                            timed[name] = (None, None, call())
                        except Exception as error:
                            timed[name] = (None, None, error)
                for name, (ms, ms_min, image) in timed.items():
                    row = {"image": image_name, "bits": bits, "file": file_name,
                           "decoder": name}
                    if isinstance(image, Exception):
                        decoded_rows.append({**row,
                                             "error": f"{type(image).__name__}: {image}"})
                        continue
                    if image is None:
                        continue  # fpng: not its file
                    ok = same(image, source)
                    decoded_rows.append({**row, "ms": ms and round(ms, 2),
                                         "ms_min": ms_min and round(ms_min, 2), "same": ok})
                    if ms is not None:
                        print(f"decode {image_name:6} {bits:2}-bit {file_name[:60]:60} "
                              f"{name:40} {ms:8.1f} ms same={ok}", file=say, flush=True)
    return encoded_rows, decoded_rows


def read_path(data: bytes) -> np.ndarray:
    """What read_image decodes with: png_codecs.decode_png, else OpenCV."""
    image = png_codecs.decode_png(data)
    if image is None:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    return image


def thread_scaling(runs: int) -> list[dict]:
    """Images a second through a pool of 1, 2, 4, ... threads up to the cores, per codec.

    The noisy and the smooth image, 8 and 16 bits; each rate the best of ``runs`` pool runs
    of at least 8 images and 2 per thread. A codec that holds the GIL gains nothing from more
    threads. Besides gpu_blur's read path as it is, each inflater's own path (libdeflate,
    ISA-L without its slots), to show why the read path uses it as it does.
    """
    from concurrent.futures import ThreadPoolExecutor

    cores = os.cpu_count() or 1
    counts = sorted({1, cores, *(2**k for k in range(1, 8) if 2**k < cores)})
    spng = optional("pyspng")
    inflaters = [found for found in (png_codecs._libdeflate_inflater(),
                                     png_codecs._isal_inflater()) if found]
    rows = []
    for image in ("noisy", "smooth"):
        values = images()[image][1]
        for bits in (8, 16):
            source = codes(values, bits)
            default = cv2.imencode(".png", bgr(source))[1].tobytes()
            jobs = {
                "decode: OpenCV imdecode (OpenCV's default file)":
                    lambda d=default: cv2.imdecode(np.frombuffer(d, np.uint8),
                                                   cv2.IMREAD_UNCHANGED),
                "decode: gpu_blur's read path (OpenCV's default file)":
                    lambda d=default: read_path(d),
            }
            for name, inflate in inflaters:
                library = {"deflate": "libdeflate", "isal": "ISA-L"}[name]
                jobs[f"decode: {library}'s inflate and numpy, every file (OpenCV's default "
                     "file)"] = lambda d=default, f=inflate: png_codecs._decode(f, d)
            if image == "noisy":
                jobs.update({
                    "encode: OpenCV default": lambda s=source: cv2.imencode(".png", bgr(s)),
                    "encode: gpu_blur output.png = fast": lambda s=source: encode_png(s, "fast"),
                    "encode: gpu_blur output.png = small":
                        lambda s=source: encode_png(s, "small"),
                })
            if spng is not None:
                jobs["decode: pyspng (OpenCV's default file)"] = lambda d=default: spng.load(d)
            for name, job in jobs.items():
                job()
                for threads in counts:
                    count = max(8, 2 * threads)
                    best = math.inf
                    with ThreadPoolExecutor(threads) as pool:
                        for _ in range(runs):
                            start = time.perf_counter()
                            list(pool.map(lambda _, job=job: job(), range(count)))
                            best = min(best, time.perf_counter() - start)
                    rows.append({"image": image, "bits": bits, "codec": name,
                                 "threads": threads, "images_per_s": round(count / best, 2)})
                    print(f"{image:6} {bits:2}-bit {name:70} {threads:3} threads "
                          f"{count / best:8.1f} images/s", flush=True)
    return rows


def seunglab_rows(args, core) -> tuple[list, list]:
    """pyspng-seunglab's rows, measured by a child process (see the module's docstring)."""
    command = [sys.executable, __file__, "--child", "--seunglab", args.seunglab,
               "--runs", str(args.runs), "--images", args.images]
    if core is not None:
        command += ["--core", str(core)]
    out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    encoded, decoded = json.loads(out)
    return ([r for r in encoded if "seunglab" in r["encoder"]],
            [r for r in decoded if "seunglab" in r["decoder"] + r["file"]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=7)
    parser.add_argument("--images", default="noisy,smooth,coffee")
    parser.add_argument("--seunglab", help="folder pyspng-seunglab was installed in (--target)")
    parser.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    parser.add_argument("--core", type=int, default=None, help="the core to pin (default: last)")
    parser.add_argument("--threads", action="store_true",
                        help="only images/s through 1, 2, 4, ... threads up to the cores "
                        "(not pinned), to bench/results/png_codecs_threads_<cpu>.json")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args()
    if args.threads:
        cv2.setNumThreads(1)
        rows = thread_scaling(3)
        path = args.json or (Path(__file__).parent / "results"
                             / f"png_codecs_threads_{cpu_tag(cpu_name())}.json")
        path.write_text(json.dumps({
            "what": ("PNG codecs through a pool of threads, images a second (best of 3 pool "
                     "runs of max(8, 2 x threads) images), the noisy and smooth 1920 x 1200 "
                     "images of bench/png_codecs.py (encoders: noisy only); OpenCV on one "
                     "thread per call; a codec holding the GIL does not scale"),
            "machine": machine(), "load_average_after": load_average(),
            "commit": source_commit(), "libraries": library_versions(),
            "rows": rows}, indent=1) + "\n")
        print(f"wrote {path}")
        return
    cv2.setNumThreads(1)
    core = None
    if hasattr(os, "sched_setaffinity"):
        core = args.core if args.core is not None else max(os.sched_getaffinity(0))
        os.sched_setaffinity(0, {core})
    enc, dec = encoders(args), decoders(args)
    all_images = images()
    encoded_rows, decoded_rows = measure(args, enc, dec, all_images)
    if args.child:
        print(json.dumps([encoded_rows, decoded_rows]))
        return
    if args.seunglab:
        more = seunglab_rows(args, core)
        encoded_rows += more[0]
        decoded_rows += more[1]
    libraries = library_versions()
    result = {
        "what": ("PNG encode and decode of RGB images, one core: ms an image (median of "
                 f"{args.runs} after a warm-up; ms_min the fastest), MB an image, and same: "
                 "whether the decoded codes equal the source's exactly (encoders: decoded "
                 "back by OpenCV; decoders: to an RGB array, OpenCV's time includes its "
                 "BGR -> RGB swap)"),
        "machine": {**machine(), "pinned_core": core, "opencv_threads": 1},
        "load_average_after": load_average(),
        "commit": source_commit(),
        "libraries": libraries,
        "missing": MISSING,
        "images": {n: {"what": all_images[n][0]} for n in args.images.split(",")},
        "encode": encoded_rows,
        "decode": decoded_rows,
    }
    path = args.json or (Path(__file__).parent / "results"
                         / f"png_codecs_{cpu_tag(cpu_name())}.json")
    path.write_text(json.dumps(result, indent=1) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
