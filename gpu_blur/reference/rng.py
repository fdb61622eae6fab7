"""Counter-based random numbers: Philox4x32-10, and the uniforms and normals drawn from it.

One generator serves the whole package: Philox4x32 with 10 rounds (Salmon, Moraes, Dror and
Shaw, "Parallel random numbers: as easy as 1, 2, 3", SC'11), exactly as Random123 specifies it
(the round and key schedule match ``pyopencl/cl/pyopencl-random123/philox.cl``, which the
OpenCL kernels include, and Random123's published known-answer vectors). A draw is a pure
function of ``(seed, counter)``, so numpy, OpenCL and Warp produce the same bits for the same
pixel however the image is tiled or scheduled. Poisson counts, drawn from the same counters,
are :mod:`gpu_blur.reference.poisson_counts`'s.

Key and counter layout (a contract with the kernels)
-----------------------------------------------------
key
    ``(seed & 0xFFFFFFFF, seed >> 32)`` for a 64-bit seed (:func:`key_from_seed`).
per-pixel draws
    ``counter = (x, y, sample_index, (stream << 24) | round)``. ``x`` and ``y`` are the pixel's
    *global* column and row in the full image (never tile-local), so tiling never changes a
    draw. ``round`` in ``[0, 2**24)`` numbers successive blocks of four words for one pixel.
per-image draws
    element ``i`` of a stream is word ``i % 4`` of ``counter = (i // 4, keyed, index,
    stream << 24)``: ``keyed`` 0 (:attr:`Keyed.SAMPLE`) and ``index`` the sample index for a
    sample's own draws; ``keyed`` 1 (:attr:`Keyed.SEQUENCE`) and ``index`` the sequence's for
    the draws every window of one frame sequence shares (``blur.draws = "per-sequence"``).
``sample_index``
    in ``[0, 2**32)``: which sample (image, frame) of a data set the draw belongs to.
``stream``
    a :class:`Stream` value in the top 8 bits of counter word 3. Each stream is used either
    per pixel or per image, never both: the per-image counter ``(j, k, s, stream << 24)``
    equals the per-pixel counter of pixel ``(x=j, y=k)`` at round 0 of the same stream. A
    sequence's draws (word 1 = 1) therefore never meet a sample's (word 1 = 0), whatever the
    two indices, and a sample's draws are the same whether or not sequences are drawn.

Uniforms
--------
A 32-bit word becomes ``u = ((bits >> 9) + 0.5) * 2**-23`` (:func:`uniform_from_bits`): the
top 23 bits, centred in their cell. ``u`` is an odd multiple of ``2**-24`` in
``[2**-24, 1 - 2**-24]``: never 0 or 1, and exactly representable in float32 (at most 24
significant bits), so a float32 kernel computing ``((float)(bits >> 9) + 0.5f) * 0x1p-23f`` gets
the identical value with no rounding at all.

Normals
-------
Normals come from the Box-Muller transform (:func:`box_muller`, :func:`pixel_normals`), written
as plain scalar arithmetic so OpenCL C and Warp can repeat it operation for operation. Its
``log``, ``sin`` and ``cos`` are :mod:`gpu_blur.reference.fixedmath`'s (IEEE operations only,
within 1 ulp), not numpy's, whose SIMD paths differ by CPU: the reference's normals have the
same bits on every machine; the kernels' libm stays within the tolerance rows of
:mod:`gpu_blur.tolerances`.
"""

from __future__ import annotations

import enum
import math

import numpy as np

from gpu_blur.reference import fixedmath

__all__ = [
    "Keyed",
    "Stream",
    "box_muller",
    "image_uniforms",
    "image_uniforms_batch",
    "key_from_seed",
    "philox4x32",
    "pixel_bits",
    "pixel_normals",
    "pixel_uniforms",
    "uniform_from_bits",
]

# Philox4x32 constants (Salmon et al. SC'11; Random123's PHILOX_M4x32_0/1 and PHILOX_W32_0/1):
# the round multipliers and the Weyl-sequence key increments (golden ratio, sqrt(3) - 1).
PHILOX_M4X32_0 = np.uint64(0xD2511F53)
PHILOX_M4X32_1 = np.uint64(0xCD9E8D57)
PHILOX_W32_0 = np.uint64(0x9E3779B9)
PHILOX_W32_1 = np.uint64(0xBB67AE85)
#: Random123's philox4x32_R asserts R <= 16.
PHILOX_MAX_ROUNDS = 16

_MASK32 = np.uint64(0xFFFFFFFF)
_SHIFT32 = np.uint64(32)
_UINT32_LIMIT = 2**32
#: Counters :func:`philox4x32` works on at a time: its uint64 temporaries (a few hundred KiB)
#: stay in a core's cache (600 x 960 counters: 76-168 -> 22 ms on a 2-core EPYC).
PHILOX_CHUNK = 1 << 14
#: Bits of counter word 3 below the stream byte, available for the round number.
_ROUND_LIMIT = 2**24

#: The uniform's scale: 23 kept bits (see the module docstring).
_UNIFORM_SHIFT = np.uint32(9)
_UNIFORM_SCALE = 2.0**-23

_TWO_PI = 2.0 * math.pi


class Stream(enum.IntEnum):
    """Independent families of draws; the value goes into the top 8 bits of counter word 3.

    PARAMS, TRAJECTORY, KERNEL and SPOT_CHECK are per-image streams (drawn with
    :func:`image_uniforms`); SHOT_NOISE, READ_NOISE and SRGB_NOISE are per-pixel streams
    (:func:`pixel_bits` and what builds on it).
    """

    PARAMS = 1  #: per-image scalar draws (WB gains, noise levels, saturation scale, ...)
    TRAJECTORY = 2  #: camera-motion trajectory
    KERNEL = 3  #: blur-kernel draws
    SHOT_NOISE = 4  #: Poisson shot noise, one count per RAW sample
    READ_NOISE = 5  #: Gaussian read noise, one normal per RAW sample
    SRGB_NOISE = 6  #: Gaussian noise added in sRGB, three normals per pixel
    SPOT_CHECK = 7  #: which tiles a spot check recomputes (gpu_blur.scheduler), one per tile


class Keyed(enum.IntEnum):
    """What the index of a per-image draw numbers; the value is counter word 1.

    A sample's draws and a frame sequence's draws (shared by the sequence's windows under
    ``blur.draws = "per-sequence"``) come from the same streams, apart by this word.
    """

    SAMPLE = 0  #: the index is a sample's (every data set before per-sequence draws)
    SEQUENCE = 1  #: the index is a frame sequence's, in the order the input lists them


# --------------------------------------------------------------------------------------------
# Philox4x32
# --------------------------------------------------------------------------------------------


def _as_words(values, name: str, last: int) -> np.ndarray:
    """Check an integer array whose last axis has ``last`` words in ``[0, 2**32)``; as uint64."""
    arr = np.asarray(values)
    if arr.ndim == 0 or arr.shape[-1] != last:
        raise ValueError(f"{name} must have shape (..., {last}); got {arr.shape}")
    if arr.dtype == np.uint32:
        return arr.astype(np.uint64)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must hold integers (uint32 words); got dtype {arr.dtype}")
    if arr.size and (arr.min() < 0 or arr.max() >= _UINT32_LIMIT):
        raise ValueError(
            f"{name} words must lie in [0, 2**32); got range [{arr.min()}, {arr.max()}]"
        )
    return arr.astype(np.uint64)


def philox4x32(counter, key, rounds: int = 10) -> np.ndarray:
    """Philox4x32-R block function, vectorized over leading axes.

    Each round (Random123 ``_philox4x32round``) takes the counter ``(c0, c1, c2, c3)`` and key
    ``(k0, k1)`` to::

        hi0:lo0 = 0xD2511F53 * c0        (32 x 32 -> 64-bit product)
        hi1:lo1 = 0xCD9E8D57 * c2
        (c0, c1, c2, c3) <- (hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0)

    and before every round but the first the key is bumped, ``k0 += 0x9E3779B9``,
    ``k1 += 0xBB67AE85`` (mod 2**32). The products are formed exactly in uint64.

    Args:
        counter: uint32 words, shape ``(..., 4)``.
        key: uint32 words, shape ``(..., 2)``; leading axes broadcast against ``counter``'s.
        rounds: number of rounds, 0 to 16 (Random123's limit); 10 is the standard Philox4x32-10.

    Returns:
        uint32 array of shape ``broadcast(counter[..., 0], key[..., 0]).shape + (4,)``.

    Raises:
        ValueError: if a shape, dtype, word value or ``rounds`` is out of range.
    """
    if isinstance(rounds, bool) or not isinstance(rounds, (int, np.integer)):
        raise ValueError(f"rounds must be an int in [0, {PHILOX_MAX_ROUNDS}]; got {rounds!r}")
    if not 0 <= rounds <= PHILOX_MAX_ROUNDS:
        raise ValueError(f"rounds must lie in [0, {PHILOX_MAX_ROUNDS}]; got {rounds}")
    ctr = _as_words(counter, "counter", 4)
    k = _as_words(key, "key", 2)
    shape = np.broadcast_shapes(ctr.shape[:-1], k.shape[:-1])
    words = np.broadcast_to(ctr, shape + (4,)).reshape(-1, 4)
    one_key = k.size == 2  # the usual case: the key stays two scalars
    keys = k.reshape(2) if one_key else np.broadcast_to(k, shape + (2,)).reshape(-1, 2)
    out = np.empty(words.shape, np.uint32)
    for start in range(0, len(words), PHILOX_CHUNK):  # temporaries that stay in cache
        block = slice(start, start + PHILOX_CHUNK)
        c0, c1, c2, c3 = words[block].T.copy()
        k0, k1 = keys if one_key else keys[block].T
        prod0, prod1 = np.empty_like(c0), np.empty_like(c0)
        for r in range(rounds):
            if r > 0:
                k0 = (k0 + PHILOX_W32_0) & _MASK32
                k1 = (k1 + PHILOX_W32_1) & _MASK32
            np.multiply(c0, PHILOX_M4X32_0, out=prod0)
            np.multiply(c2, PHILOX_M4X32_1, out=prod1)
            # (c0, c1, c2, c3) <- (hi1 ^ c1 ^ k0, lo1, hi0 ^ c3 ^ k1, lo0), in place
            np.right_shift(prod1, _SHIFT32, out=c0)
            c0 ^= c1
            c0 ^= k0
            np.bitwise_and(prod1, _MASK32, out=c1)
            np.right_shift(prod0, _SHIFT32, out=c2)
            c2 ^= c3
            c2 ^= k1
            np.bitwise_and(prod0, _MASK32, out=c3)
        out[block] = np.stack([c0, c1, c2, c3], axis=-1)
    return out.reshape(shape + (4,))


# --------------------------------------------------------------------------------------------
# Keys, counters and their checks
# --------------------------------------------------------------------------------------------


def key_from_seed(seed: int) -> np.ndarray:
    """Split a 64-bit seed into the Philox key ``(seed & 0xFFFFFFFF, seed >> 32)``.

    Args:
        seed: int in ``[0, 2**64)`` (Python or numpy integer; bool is refused).

    Returns:
        uint32 array of shape ``(2,)``.

    Raises:
        ValueError: if ``seed`` is not an integer or is out of range.
    """
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"seed must be an int in [0, 2**64); got {seed!r}")
    seed = int(seed)
    if not 0 <= seed < 2**64:
        raise ValueError(f"seed must lie in [0, 2**64); got {seed}")
    return np.array([seed & 0xFFFFFFFF, seed >> 32], dtype=np.uint32)


def _check_sample_index(sample_index) -> int:
    if isinstance(sample_index, bool) or not isinstance(sample_index, (int, np.integer)):
        raise ValueError(f"sample_index must be an int in [0, 2**32); got {sample_index!r}")
    if not 0 <= int(sample_index) < _UINT32_LIMIT:
        raise ValueError(f"sample_index must lie in [0, 2**32); got {sample_index}")
    return int(sample_index)


def _check_stream(stream) -> Stream:
    try:
        return Stream(stream)
    except ValueError:
        raise ValueError(
            f"stream must be a gpu_blur.reference.rng.Stream; got {stream!r} "
            f"(known: {', '.join(f'{s.name}={s.value}' for s in Stream)})"
        ) from None


def _check_keyed(keyed) -> Keyed:
    try:
        return Keyed(keyed)
    except ValueError:
        raise ValueError(f"keyed must be a gpu_blur.reference.rng.Keyed (SAMPLE=0, "
                         f"SEQUENCE=1); got {keyed!r}") from None


def _check_round(round) -> int:
    if isinstance(round, bool) or not isinstance(round, (int, np.integer)):
        raise ValueError(f"round must be an int in [0, 2**24); got {round!r}")
    if not 0 <= int(round) < _ROUND_LIMIT:
        raise ValueError(f"round must lie in [0, 2**24); got {round}")
    return int(round)


def _check_coordinate(values, name: str) -> np.ndarray:
    arr = np.asarray(values)
    if not np.issubdtype(arr.dtype, np.integer):
        raise ValueError(f"{name} must be integer pixel coordinates; got dtype {arr.dtype}")
    if arr.size and (arr.min() < 0 or arr.max() >= _UINT32_LIMIT):
        raise ValueError(
            f"{name} must lie in [0, 2**32) (global pixel coordinates); "
            f"got range [{arr.min()}, {arr.max()}]"
        )
    return arr.astype(np.uint32)


# --------------------------------------------------------------------------------------------
# Uniforms
# --------------------------------------------------------------------------------------------


def uniform_from_bits(bits) -> np.ndarray:
    """Map 32-bit words to uniforms ``u = ((bits >> 9) + 0.5) * 2**-23`` in (0, 1).

    ``u`` is an odd multiple of ``2**-24`` between ``2**-24`` and ``1 - 2**-24`` (bits 0 and
    0xFFFFFFFF give exactly those ends), so it is never 0 or 1. With at most 24 significant
    bits it is exact in float32 as well: a float32 kernel evaluating the same expression gets
    the same value, bit for bit. (Keeping 24 bits, ``((bits >> 8) + 0.5) * 2**-24``, would
    need 25 significant bits for ``u >= 0.5`` and round in float32; the top value would round
    to 1.0.)

    Args:
        bits: integer array of words in ``[0, 2**32)``, any shape.

    Returns:
        float64 array of the same shape.
    """
    arr = np.asarray(bits)
    if arr.dtype != np.uint32:
        if not np.issubdtype(arr.dtype, np.integer):
            raise ValueError(f"bits must be uint32 words; got dtype {arr.dtype}")
        if arr.size and (arr.min() < 0 or arr.max() >= _UINT32_LIMIT):
            raise ValueError(f"bits must lie in [0, 2**32); got range [{arr.min()}, {arr.max()}]")
        arr = arr.astype(np.uint32)
    return ((arr >> _UNIFORM_SHIFT).astype(np.float64) + 0.5) * _UNIFORM_SCALE


def image_uniforms(seed: int, sample_index: int, stream: Stream, count: int,
                   keyed: Keyed = Keyed.SAMPLE) -> np.ndarray:
    """Return the first ``count`` per-image uniforms of a stream.

    Element ``i`` is word ``i % 4`` of ``philox4x32((i // 4, keyed, sample_index, stream <<
    24), key_from_seed(seed))``, through :func:`uniform_from_bits`. Asking for more elements
    never changes the earlier ones.

    Args:
        seed: 64-bit seed.
        sample_index: sample number in ``[0, 2**32)`` (a sequence's with
            :attr:`Keyed.SEQUENCE`).
        stream: a per-image :class:`Stream` (PARAMS, TRAJECTORY, KERNEL, SPOT_CHECK).
        count: number of uniforms, >= 0.
        keyed: what ``sample_index`` numbers (:class:`Keyed`): a sample (default) or a
            frame sequence.

    Returns:
        float64 array of shape ``(count,)``, values in (0, 1).
    """
    key = key_from_seed(seed)
    sample_index = _check_sample_index(sample_index)
    stream = _check_stream(stream)
    keyed = _check_keyed(keyed)
    blocks = _blocks_of(count)
    if blocks <= _SCALAR_BLOCKS:  # a sample's few draws: Python ints beat numpy's set-up
        k0, k1 = int(key[0]), int(key[1])
        words = [w for b in range(blocks)
                 for w in _philox4x32_ints(b, int(keyed), sample_index, int(stream) << 24,
                                           k0, k1)]
        shift = int(_UNIFORM_SHIFT)
        return np.array([((w >> shift) + 0.5) * _UNIFORM_SCALE for w in words[:count]])
    return image_uniforms_batch(seed, [sample_index], stream, count, keyed)[0]


def image_uniforms_batch(seed: int, sample_indices, stream: Stream, count: int,
                         keyed: Keyed = Keyed.SAMPLE) -> np.ndarray:
    """:func:`image_uniforms` of several samples at once: row b is sample_indices[b]'s.

    One Philox evaluation over every sample's blocks, for a batch's per-image draws (numpy's
    set-up costs about as much for one sample's blocks as for sixteen); up to
    ``_SCALAR_BLOCKS`` blocks in all, each sample on Python ints as :func:`image_uniforms`.

    Returns:
        float64 array of shape ``(len(sample_indices), count)``.
    """
    indices = [_check_sample_index(i) for i in sample_indices]
    blocks = _blocks_of(count)
    keyed = _check_keyed(keyed)
    if blocks * len(indices) <= _SCALAR_BLOCKS:  # a sample or two of few draws
        return np.array([image_uniforms(seed, i, stream, count, keyed)
                         for i in indices]).reshape(len(indices), count)
    key = key_from_seed(seed)
    stream = _check_stream(stream)
    counter = np.zeros((len(indices), blocks, 4), dtype=np.uint64)
    counter[:, :, 0] = np.arange(blocks, dtype=np.uint64)
    counter[:, :, 1] = int(keyed)
    counter[:, :, 2] = np.asarray(indices, dtype=np.uint64)[:, None]
    counter[:, :, 3] = int(stream) << 24
    bits = philox4x32(counter.reshape(-1, 4), key)
    return uniform_from_bits(bits.reshape(len(indices), -1)[:, :count])


#: Blocks up to which :func:`image_uniforms` runs Philox on Python ints (a sample's parameter
#: draws: 3 blocks, about 40 us instead of 150 us through numpy's per-call overheads).
_SCALAR_BLOCKS = 8


def _blocks_of(count) -> int:
    """Philox blocks (4 words each) holding ``count`` uniforms; refuses a bad count."""
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 0:
        raise ValueError(f"count must be a non-negative int; got {count!r}")
    blocks = -(-int(count) // 4)
    if blocks > _UINT32_LIMIT:
        raise ValueError(f"count must be at most 4 * 2**32; got {count}")
    return blocks


def _philox4x32_ints(c0: int, c1: int, c2: int, c3: int, k0: int, k1: int
                     ) -> tuple[int, int, int, int]:
    """:func:`philox4x32` (10 rounds) of one counter on Python ints: the same exact words."""
    m0, m1, w0, w1 = (int(c) for c in (PHILOX_M4X32_0, PHILOX_M4X32_1, PHILOX_W32_0,
                                       PHILOX_W32_1))
    mask = int(_MASK32)
    for r in range(10):
        if r > 0:
            k0, k1 = (k0 + w0) & mask, (k1 + w1) & mask
        p0, p1 = m0 * c0, m1 * c2
        c0, c1, c2, c3 = (p1 >> 32) ^ c1 ^ k0, p1 & mask, (p0 >> 32) ^ c3 ^ k1, p0 & mask
    return c0, c1, c2, c3


def pixel_bits(seed: int, sample_index: int, stream: Stream, y, x, round: int = 0) -> np.ndarray:
    """Raw Philox words for pixels at global row ``y`` and column ``x``.

    ``counter = (x, y, sample_index, (stream << 24) | round)``, ``key = key_from_seed(seed)``.

    Args:
        seed: 64-bit seed.
        sample_index: sample number in ``[0, 2**32)``.
        stream: a per-pixel :class:`Stream`.
        y: integer array (or int) of global rows in ``[0, 2**32)``.
        x: integer array (or int) of global columns; broadcast against ``y``.
        round: block number in ``[0, 2**24)``; each round gives four fresh words per pixel.

    Returns:
        uint32 array of shape ``broadcast(y, x).shape + (4,)``.
    """
    key = key_from_seed(seed)
    sample_index = _check_sample_index(sample_index)
    stream = _check_stream(stream)
    round = _check_round(round)
    yy = _check_coordinate(y, "y")
    xx = _check_coordinate(x, "x")
    shape = np.broadcast_shapes(yy.shape, xx.shape)
    counter = np.empty(shape + (4,), dtype=np.uint32)
    counter[..., 0] = xx
    counter[..., 1] = yy
    counter[..., 2] = sample_index
    counter[..., 3] = (int(stream) << 24) | round
    return philox4x32(counter, key)


def pixel_uniforms(
    seed: int, sample_index: int, stream: Stream, y, x, round: int = 0
) -> np.ndarray:
    """:func:`pixel_bits` through :func:`uniform_from_bits`: float64 ``(..., 4)`` in (0, 1)."""
    return uniform_from_bits(pixel_bits(seed, sample_index, stream, y, x, round))


# --------------------------------------------------------------------------------------------
# Normals
# --------------------------------------------------------------------------------------------


def box_muller(u1, u2) -> tuple[np.ndarray, np.ndarray]:
    """Box-Muller transform of two uniforms into two independent standard normals.

    ``r = sqrt(-2 * log(u1))``, ``t = (2 * pi) * u2``; returns ``(r * cos(t), r * sin(t))``
    (Box and Muller, "A note on the generation of random normal deviates", Ann. Math. Statist.
    29, 1958), ``log``, ``sin`` and ``cos`` from :mod:`~gpu_blur.reference.fixedmath` (one
    reduction for both). With ``u1 >= 2**-24`` (:func:`uniform_from_bits`) ``|z| <= 5.77``:
    the tails beyond are cut, a probability of about 8e-9.

    Args:
        u1: uniforms in (0, 1], any shape.
        u2: uniforms in [0, 1], broadcast against ``u1``.

    Returns:
        ``(z_cos, z_sin)``, float64 arrays of the broadcast shape.
    """
    u1 = np.asarray(u1, dtype=np.float64)
    u2 = np.asarray(u2, dtype=np.float64)
    radius = np.sqrt(-2.0 * fixedmath.log(u1))
    sin_t, cos_t = fixedmath.sincos(_TWO_PI * u2)
    return radius * cos_t, radius * sin_t


def pixel_normals(seed: int, sample_index: int, stream: Stream, y, x, count: int) -> np.ndarray:
    """``count`` standard normals per pixel, four per Philox round.

    Round ``r`` gives uniforms ``(w0, w1, w2, w3)`` (:func:`pixel_uniforms`); normals
    ``4r, 4r + 1`` are ``box_muller(w0, w1)`` (cos, sin) and normals ``4r + 2, 4r + 3`` are
    ``box_muller(w2, w3)``. Normal ``j`` therefore comes from round ``j // 4``, and asking for
    more normals never changes the earlier ones.

    Args:
        seed: 64-bit seed.
        sample_index: sample number in ``[0, 2**32)``.
        stream: a per-pixel :class:`Stream`.
        y: integer array of global rows.
        x: integer array of global columns; broadcast against ``y``.
        count: normals per pixel, >= 1.

    Returns:
        float64 array of shape ``broadcast(y, x).shape + (count,)``.
    """
    if isinstance(count, bool) or not isinstance(count, (int, np.integer)) or count < 1:
        raise ValueError(f"count must be a positive int; got {count!r}")
    blocks = []
    for r in range(-(-int(count) // 4)):
        u = pixel_uniforms(seed, sample_index, stream, y, x, round=r)
        z0, z1 = box_muller(u[..., 0], u[..., 1])
        z2, z3 = box_muller(u[..., 2], u[..., 3])
        blocks.append(np.stack([z0, z1, z2, z3], axis=-1))
    return np.concatenate(blocks, axis=-1)[..., :count]

