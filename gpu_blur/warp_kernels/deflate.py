"""PNG rows Sub-filtered and deflated with Huffman codes alone, on the device: zlib's bytes.

The stream :func:`gpu_blur.png_codecs.huffman_zlib` writes for ``output.png = "fast"``, made
where the codes already are. zlib (and zlib-ng, which writes the same bytes for this strategy)
decides everything per block, and a block is a fixed run of the input, so the blocks are
independent until their bits are laid end to end:

* ``deflate_huff`` (deflate.c) tallies one literal per input byte and ends a block every
  ``lit_bufsize - 1`` = 16,383 literals (``memLevel`` 8: ``lit_bufsize = 1 << (8 + 6)``); the
  last block takes the rest, perhaps none.
* ``_tr_flush_block`` (trees.c) builds the block's literal tree (its byte counts, and 1 for
  the end-of-block code), the distance tree (no distances: two codes of one bit), the tree of
  code lengths, and writes the block stored, with the fixed codes or with its own, whichever
  its byte counts say is smallest, ties as zlib breaks them.

Reproduced here, in the order zlib does each step (its heap and tie-breaks, its repair of codes
longer than 15 bits, its run-length coding of the code lengths), so the bytes are zlib's:
tests/io/test_png_device.py checks them against the installed zlib's (zlib-ng's or Python's) on
images that reach each branch. Six kernels in five steps over a batch of images, each image's
blocks ``(image, block)`` and their segments of :data:`SEGMENT` literals:

1. :func:`count_kernel`: each block's byte counts, and each segment's two Adler-32 sums;
2. :func:`trees_kernel`: a thread a block builds its trees, chooses its kind and writes its
   header bits (and its end-of-block code's place);
3. :func:`sizes_kernel`: each segment's bits, then :func:`offsets_kernel` their running sums
   in each block;
4. :func:`layout_kernel`: a thread an image lays the blocks end to end (stored blocks on a
   byte boundary) and finishes the Adler-32;
5. :func:`write_kernel`: each segment writes its codes' bits, each block its header, by adding
   them into the zeroed output words (the bits of two writers never overlap, so an atomic add
   is an OR).

Words are little-endian, bit 0 first, as deflate packs bits (RFC 1951, 3.1.1).
"""

import numpy as np
import warp as wp

__all__ = ["BLOCK", "HEADER_WORDS", "HEAP", "SEGMENT", "SEGMENTS", "count_kernel",
           "layout_kernel", "offsets_kernel", "sizes_kernel", "static_codes", "trees_kernel",
           "write_kernel"]

wp.set_module_options({"enable_backward": False})

#: Literals of a block but the last: zlib's ``lit_bufsize - 1`` at ``memLevel`` 8.
BLOCK = 16383
#: Literals a thread of the segment kernels takes.
SEGMENT = 64
#: Segments of a block.
SEGMENTS = (BLOCK + SEGMENT - 1) // SEGMENT
#: Nodes of zlib's heap (``HEAP_SIZE``: 2 * 286 + 1).
HEAP = 573
#: Header words a block holds: 3 + 14 + 19 * 3 bits, then at most 316 code lengths of 7 bits
#: and 7 more bits each.
HEADER_WORDS = 144
#: Rows of tree scratch a block holds: literal/length, distance, code lengths.
TREES = 3
_ADLER = 65521  # the largest prime below 2^16 (RFC 1950, 8.2)

# block kinds, BTYPE (RFC 1951, 3.2.3)
_STORED = 0
_FIXED = 1
_DYNAMIC = 2

# the columns of a block's row of ``info``
_KIND = 0
_HEADER_BITS = 1   # bits from the block's start to its first literal (stored: 3)
_DATA_BITS = 2     # its literals' bits and the end-of-block code's
_START = 3         # its first bit in the image's stream
_SUM_A = 4         # its bytes' sum, modulo 65521
_SUM_B = 5         # its bytes' weighted sum, modulo 65521
_END_CODE = 6      # bits of its end-of-block code (0 for stored)
BLOCK_COLUMNS = 8


def static_codes() -> np.ndarray:
    """The fixed literal codes 0-256 (RFC 1951, 3.2.6), bit-reversed: 2 x 257 int32.

    Row 0 the codes, row 1 their lengths.
    """
    lengths = np.array([8] * 144 + [9] * 112 + [7] * 24 + [8] * 8)
    codes = np.zeros(288, np.int64)
    code, next_code = 0, {}
    for bits in range(1, 16):
        code = (code + int(np.sum(lengths == bits - 1))) << 1
        next_code[bits] = code
    for n, bits in enumerate(lengths):
        reversed_code = int(format(next_code[bits], f"0{bits}b")[::-1], 2)
        codes[n], next_code[bits] = reversed_code, next_code[bits] + 1
    return np.stack([codes[:257], lengths[:257]]).astype(np.int32)


@wp.func
def _literal(codes: wp.array(dtype=wp.uint8), base: int, i: int, stride: int, channels: int
             ) -> int:
    """Byte i of an image's Sub-filtered rows (PNG 9.2).

    1 at a row's start, else the code less the one a pixel to its left, modulo 256.
    """
    row = i / stride
    col = i - row * stride
    if col == 0:
        return 1
    at = base + row * (stride - 1) + col - 1
    value = int(codes[at])
    if col > channels:
        value = (value - int(codes[at - channels])) & 255
    return value


@wp.kernel
def count_kernel(codes: wp.array(dtype=wp.uint8), pixels: int, stride: int, channels: int,
                 total: int, blocks: int, counts: wp.array2d(dtype=wp.int32),
                 sums: wp.array3d(dtype=wp.int64)):
    """Each block's byte counts, and each segment's two Adler-32 sums.

    ``counts[image * blocks + block]``; ``sums[..., segment]``: the sum of its bytes, and
    their sum weighted by ``total - i`` (RFC 1950's Adler-32, split).
    """
    image, block, segment = wp.tid()
    first = block * BLOCK + segment * SEGMENT
    last = wp.min(wp.min(first + SEGMENT, (block + 1) * BLOCK), total)
    g = image * blocks + block
    a = wp.int64(0)
    b = wp.int64(0)
    for i in range(first, last):
        value = _literal(codes, image * pixels, i, stride, channels)
        wp.atomic_add(counts, g, value, 1)
        a += wp.int64(value)
        b += wp.int64(total - i) * wp.int64(value)
    sums[g, segment, 0] = a
    sums[g, segment, 1] = b


@wp.func
def _smaller(freq: wp.array2d(dtype=wp.int32), depth: wp.array2d(dtype=wp.int32), row: int,
             n: int, m: int) -> bool:
    """As zlib's ``smaller``: the lower count, on ties the shallower (or equal) subtree."""
    a = freq[row, n]
    b = freq[row, m]
    return a < b or (a == b and depth[row, n] <= depth[row, m])


@wp.func
def _down_heap(freq: wp.array2d(dtype=wp.int32), depth: wp.array2d(dtype=wp.int32),
               heap: wp.array2d(dtype=wp.int32), row: int, start: int, size: int):
    """As zlib's ``pqdownheap``: the node at ``start`` sifted down the 1-based heap."""
    k = start
    v = heap[row, k]
    j = k * 2
    while j <= size:
        if j < size:
            if _smaller(freq, depth, row, heap[row, j + 1], heap[row, j]):
                j = j + 1
        if _smaller(freq, depth, row, v, heap[row, j]):
            break
        heap[row, k] = heap[row, j]
        k = j
        j = k * 2
    heap[row, k] = v


@wp.func
def _static_bits(tree: int, n: int) -> int:
    """A symbol's bits in the fixed codes: literal/length (tree 0) or distance (tree 1)."""
    if tree == 1:
        return 5
    if n < 144:
        return 8
    if n < 256:
        return 9
    if n < 280:
        return 7
    return 8


@wp.func
def _extra_bits(tree: int, n: int) -> int:
    """Extra bits of a code-length symbol (16: 2, 17: 3, 18: 7); literals have none here."""
    if tree == 2:
        if n == 16:
            return 2
        if n == 17:
            return 3
        if n == 18:
            return 7
    return 0


@wp.func
def _build_tree(freq: wp.array2d(dtype=wp.int32), dad: wp.array2d(dtype=wp.int32),
                lengths: wp.array2d(dtype=wp.int32), depth: wp.array2d(dtype=wp.int32),
                heap: wp.array2d(dtype=wp.int32), count: wp.array2d(dtype=wp.int32),
                code: wp.array2d(dtype=wp.int32), sizes: wp.array2d(dtype=wp.int64),
                row: int, tree: int, elems: int, max_length: int, g: int) -> int:
    """As zlib's ``build_tree``, ``gen_bitlen`` and ``gen_codes`` over one tree's row.

    ``tree`` 0, 1 or 2 (literal/length, distance, code lengths; the first two have fixed
    codes to size against); adds to ``sizes[g]``: 0 the block's bits with its own codes
    (``opt_len``), 1 with the fixed ones (``static_len``). Returns the largest symbol with a
    code (``max_code``).
    """
    heap_len = wp.int32(0)
    max_code = wp.int32(-1)
    for n in range(elems):
        if freq[row, n] != 0:
            heap_len += 1
            heap[row, heap_len] = n
            max_code = n
            depth[row, n] = 0
        else:
            lengths[row, n] = 0
    # at least two codes, so every symbol has one of at least one bit
    while heap_len < 2:
        node = wp.int32(0)
        if max_code < 2:
            max_code += 1
            node = max_code
        heap_len += 1
        heap[row, heap_len] = node
        freq[row, node] = 1
        depth[row, node] = 0
        sizes[g, 0] = sizes[g, 0] - wp.int64(1)
        if tree < 2:
            sizes[g, 1] = sizes[g, 1] - wp.int64(_static_bits(tree, node))
    n = heap_len / 2
    while n >= 1:
        _down_heap(freq, depth, heap, row, n, heap_len)
        n -= 1
    node = elems
    heap_max = int(HEAP)
    while heap_len >= 2:
        least = heap[row, 1]  # pqremove
        heap[row, 1] = heap[row, heap_len]
        heap_len -= 1
        _down_heap(freq, depth, heap, row, 1, heap_len)
        next_least = heap[row, 1]
        heap_max -= 1
        heap[row, heap_max] = least
        heap_max -= 1
        heap[row, heap_max] = next_least
        freq[row, node] = freq[row, least] + freq[row, next_least]
        depth[row, node] = wp.max(depth[row, least], depth[row, next_least]) + 1
        dad[row, least] = node
        dad[row, next_least] = node
        heap[row, 1] = node
        node += 1
        _down_heap(freq, depth, heap, row, 1, heap_len)
    heap_max -= 1
    heap[row, heap_max] = heap[row, 1]

    # gen_bitlen: lengths from the root down, capped at max_length
    for bits in range(16):
        count[row, bits] = 0
    lengths[row, heap[row, heap_max]] = 0
    overflow = wp.int32(0)
    for h in range(heap_max + 1, HEAP):
        n = heap[row, h]
        bits = lengths[row, dad[row, n]] + 1
        if bits > max_length:
            bits = max_length
            overflow += 1
        lengths[row, n] = bits
        if n <= max_code:
            count[row, bits] = count[row, bits] + 1
            f = wp.int64(freq[row, n])
            extra = _extra_bits(tree, n)
            sizes[g, 0] = sizes[g, 0] + f * wp.int64(bits + extra)
            if tree < 2:
                sizes[g, 1] = sizes[g, 1] + f * wp.int64(_static_bits(tree, n) + extra)
    if overflow > 0:
        while overflow > 0:
            bits = max_length - 1
            while count[row, bits] == 0:
                bits -= 1
            count[row, bits] = count[row, bits] - 1  # a leaf moves down
            count[row, bits + 1] = count[row, bits + 1] + 2  # with an overflowed one beside
            count[row, max_length] = count[row, max_length] - 1
            overflow -= 2
        # lengths again, in increasing count order
        h = int(HEAP)
        bits = max_length
        while bits != 0:
            left = count[row, bits]
            while left != 0:
                h -= 1
                m = heap[row, h]
                if m <= max_code:
                    if lengths[row, m] != bits:
                        sizes[g, 0] = sizes[g, 0] + (
                            wp.int64(bits) - wp.int64(lengths[row, m])) * wp.int64(freq[row, m])
                        lengths[row, m] = bits
                    left -= 1
            bits -= 1

    # gen_codes: canonical codes, bit-reversed for an LSB-first writer
    next_code = wp.int32(0)
    for bits in range(1, 16):
        next_code = (next_code + count[row, bits - 1]) << 1
        dad[row, bits] = next_code  # dad is free now: the first code of each length
    for n in range(max_code + 1):
        bits = lengths[row, n]
        if bits != 0:
            c = dad[row, bits]
            dad[row, bits] = c + 1
            reversed_code = wp.int32(0)
            for _ in range(bits):
                reversed_code = (reversed_code << 1) | (c & 1)
                c = c >> 1
            code[row, n] = reversed_code
    return max_code


@wp.func
def _next_length(lengths: wp.array2d(dtype=wp.int32), row: int, n: int, max_code: int) -> int:
    """A symbol's code length, or zlib's guard (0xffff) just past ``max_code``."""
    if n > max_code:
        return 0xFFFF
    return lengths[row, n]


@wp.func
def _put(words: wp.array2d(dtype=wp.uint32), g: int, at: int, value: int, bits: int) -> int:
    """``bits`` bits of ``value`` into a block's header words at bit ``at``; the next bit."""
    word = at >> 5
    shift = at & 31
    v = wp.uint64(value) << wp.uint64(shift)
    words[g, word] = words[g, word] | wp.uint32(v & wp.uint64(0xFFFFFFFF))
    if shift + bits > 32:
        words[g, word + 1] = words[g, word + 1] | wp.uint32(v >> wp.uint64(32))
    return at + bits


@wp.func
def _tree_lengths(lengths: wp.array2d(dtype=wp.int32), row: int, max_code: int,
                  freq: wp.array2d(dtype=wp.int32), code: wp.array2d(dtype=wp.int32),
                  bl_row: int, send: bool, words: wp.array2d(dtype=wp.uint32), g: int,
                  at: int) -> int:
    """A tree's code lengths as runs of code-length symbols (RFC 1951, 3.2.7); the next bit.

    As zlib's ``scan_tree`` without ``send`` (counts the symbols into ``freq[bl_row]``) and
    its ``send_tree`` with it (writes them in the code-length codes of ``bl_row`` into the
    block's header words from bit ``at``); both walk the lengths alike.
    """
    prev = wp.int32(-1)
    next_len = lengths[row, 0]
    run = wp.int32(0)
    max_count = wp.int32(7)
    min_count = wp.int32(4)
    pos = at
    if next_len == 0:
        max_count = 138
        min_count = 3
    for n in range(max_code + 1):
        cur = next_len
        next_len = _next_length(lengths, row, n + 1, max_code)
        run += 1
        if run < max_count and cur == next_len:
            continue
        if run < min_count:  # each length as itself
            if send:
                for _ in range(run):
                    pos = _put(words, g, pos, code[bl_row, cur], lengths[bl_row, cur])
            else:
                freq[bl_row, cur] = freq[bl_row, cur] + run
        elif cur != 0:  # 16: the last length again, 3-6 times
            if cur != prev:
                if send:
                    pos = _put(words, g, pos, code[bl_row, cur], lengths[bl_row, cur])
                    run -= 1
                else:
                    freq[bl_row, cur] = freq[bl_row, cur] + 1
            if send:
                pos = _put(words, g, pos, code[bl_row, 16], lengths[bl_row, 16])
                pos = _put(words, g, pos, run - 3, 2)
            else:
                freq[bl_row, 16] = freq[bl_row, 16] + 1
        elif run <= 10:  # 17: 3-10 zeros
            if send:
                pos = _put(words, g, pos, code[bl_row, 17], lengths[bl_row, 17])
                pos = _put(words, g, pos, run - 3, 3)
            else:
                freq[bl_row, 17] = freq[bl_row, 17] + 1
        else:  # 18: 11-138 zeros
            if send:
                pos = _put(words, g, pos, code[bl_row, 18], lengths[bl_row, 18])
                pos = _put(words, g, pos, run - 11, 7)
            else:
                freq[bl_row, 18] = freq[bl_row, 18] + 1
        run = 0
        prev = cur
        if next_len == 0:
            max_count = 138
            min_count = 3
        elif cur == next_len:
            max_count = 6
            min_count = 3
        else:
            max_count = 7
            min_count = 4
    return pos


@wp.kernel
def trees_kernel(counts: wp.array2d(dtype=wp.int32), total: int, blocks: int,
                 order: wp.array(dtype=wp.int32), freq: wp.array2d(dtype=wp.int32),
                 dad: wp.array2d(dtype=wp.int32), lengths: wp.array2d(dtype=wp.int32),
                 depth: wp.array2d(dtype=wp.int32), heap: wp.array2d(dtype=wp.int32),
                 bit_count: wp.array2d(dtype=wp.int32), code: wp.array2d(dtype=wp.int32),
                 sizes: wp.array2d(dtype=wp.int64), header: wp.array2d(dtype=wp.uint32),
                 fixed: wp.array2d(dtype=wp.int32), info: wp.array2d(dtype=wp.int64)):
    """A block's trees, kind and header, as zlib's ``_tr_flush_block`` decides and writes them.

    ``order``: the code-length symbols' order in the header (RFC 1951, 3.2.7); ``fixed``:
    :func:`static_codes`. Into ``info[g]``: the kind, the header's and the literals' bits, the
    end-of-block code's bits.
    """
    image, block = wp.tid()
    g = image * blocks + block
    lit = g * TREES
    dist = lit + 1
    bl = lit + 2
    stored = wp.min(BLOCK, total - block * BLOCK)  # this block's literals
    last = 0
    if block == blocks - 1:
        last = 1
    for n in range(HEAP):
        freq[lit, n] = 0
        freq[dist, n] = 0
        freq[bl, n] = 0
    for n in range(256):
        freq[lit, n] = counts[g, n]
    freq[lit, 256] = 1  # the end-of-block code
    sizes[g, 0] = wp.int64(0)
    sizes[g, 1] = wp.int64(0)
    max_lit = _build_tree(freq, dad, lengths, depth, heap, bit_count, code, sizes, lit, 0, 286,
                          15, g)
    max_dist = _build_tree(freq, dad, lengths, depth, heap, bit_count, code, sizes, dist, 1, 30,
                           15, g)
    _tree_lengths(lengths, lit, max_lit, freq, code, bl, False, header, g, 0)
    _tree_lengths(lengths, dist, max_dist, freq, code, bl, False, header, g, 0)
    _build_tree(freq, dad, lengths, depth, heap, bit_count, code, sizes, bl, 2, 19, 7, g)
    max_blindex = wp.int32(18)
    while max_blindex >= 3:
        if lengths[bl, order[max_blindex]] != 0:
            break
        max_blindex -= 1
    opt_len = sizes[g, 0] + wp.int64(3 * (max_blindex + 1) + 14)
    opt_bytes = (opt_len + wp.int64(10)) >> wp.int64(3)
    static_bytes = (sizes[g, 1] + wp.int64(10)) >> wp.int64(3)
    if static_bytes <= opt_bytes:
        opt_bytes = static_bytes
    for w in range(HEADER_WORDS):
        header[g, w] = wp.uint32(0)
    data = wp.int32(0)
    if wp.int64(stored + 4) <= opt_bytes:
        info[g, _KIND] = wp.int64(_STORED)
        info[g, _HEADER_BITS] = wp.int64(3)
        info[g, _DATA_BITS] = wp.int64(8 * stored)
        info[g, _END_CODE] = wp.int64(0)
        _put(header, g, 0, last, 3)  # BTYPE 00 after BFINAL
        return
    if static_bytes == opt_bytes:
        info[g, _KIND] = wp.int64(_FIXED)
        info[g, _HEADER_BITS] = wp.int64(_put(header, g, 0, 2 + last, 3))  # BTYPE 01
        for n in range(256):
            data += counts[g, n] * fixed[1, n]
        info[g, _DATA_BITS] = wp.int64(data + fixed[1, 256])
        info[g, _END_CODE] = wp.int64(fixed[1, 256])
        return
    pos = _put(header, g, 0, 4 + last, 3)  # BTYPE 10
    pos = _put(header, g, pos, max_lit + 1 - 257, 5)
    pos = _put(header, g, pos, max_dist + 1 - 1, 5)
    pos = _put(header, g, pos, max_blindex + 1 - 4, 4)
    for rank in range(max_blindex + 1):
        pos = _put(header, g, pos, lengths[bl, order[rank]], 3)
    pos = _tree_lengths(lengths, lit, max_lit, freq, code, bl, True, header, g, pos)
    pos = _tree_lengths(lengths, dist, max_dist, freq, code, bl, True, header, g, pos)
    for n in range(256):
        data += counts[g, n] * lengths[lit, n]
    info[g, _KIND] = wp.int64(_DYNAMIC)
    info[g, _HEADER_BITS] = wp.int64(pos)
    info[g, _DATA_BITS] = wp.int64(data + lengths[lit, 256])
    info[g, _END_CODE] = wp.int64(lengths[lit, 256])


@wp.func
def _code_of(kind: int, value: int, g: int, lit: int, code: wp.array2d(dtype=wp.int32),
             lengths: wp.array2d(dtype=wp.int32), fixed: wp.array2d(dtype=wp.int32)) -> wp.vec2i:
    """A literal's (bit-reversed code, bits) in its block's kind."""
    if kind == _STORED:
        return wp.vec2i(value, 8)
    if kind == _FIXED:
        return wp.vec2i(fixed[0, value], fixed[1, value])
    return wp.vec2i(code[lit, value], lengths[lit, value])


@wp.kernel
def sizes_kernel(codes: wp.array(dtype=wp.uint8), pixels: int, stride: int, channels: int,
                 total: int, blocks: int, info: wp.array2d(dtype=wp.int64),
                 code: wp.array2d(dtype=wp.int32), lengths: wp.array2d(dtype=wp.int32),
                 fixed: wp.array2d(dtype=wp.int32), bits: wp.array2d(dtype=wp.int32)):
    """Each segment's bits in its block's codes."""
    image, block, segment = wp.tid()
    g = image * blocks + block
    first = block * BLOCK + segment * SEGMENT
    last = wp.min(wp.min(first + SEGMENT, (block + 1) * BLOCK), total)
    kind = int(info[g, _KIND])
    n = wp.int32(0)
    for i in range(first, last):
        value = _literal(codes, image * pixels, i, stride, channels)
        n += _code_of(kind, value, g, g * TREES, code, lengths, fixed)[1]
    bits[g, segment] = n


@wp.kernel
def offsets_kernel(bits: wp.array2d(dtype=wp.int32), sums: wp.array3d(dtype=wp.int64),
                   info: wp.array2d(dtype=wp.int64)):
    """Each segment's first bit in its block's literals, and the block's Adler-32 sums.

    The offsets replace the segments' bits in ``bits``; the sums are modulo 65521.
    """
    g = wp.tid()
    at = wp.int32(0)
    a = wp.int64(0)
    b = wp.int64(0)
    for segment in range(SEGMENTS):
        n = bits[g, segment]
        bits[g, segment] = at
        at += n
        a += sums[g, segment, 0]
        b += sums[g, segment, 1]
    info[g, _SUM_A] = a % wp.int64(_ADLER)
    info[g, _SUM_B] = b % wp.int64(_ADLER)


@wp.kernel
def layout_kernel(total: int, blocks: int, info: wp.array2d(dtype=wp.int64),
                  streams: wp.array2d(dtype=wp.int64)):
    """An image's blocks end to end, each block's first bit into its ``info`` row.

    ``streams[image]``: the stream's bytes and its Adler-32.
    """
    image = wp.tid()
    at = wp.int64(0)
    a = wp.int64(1)
    b = wp.int64(total) % wp.int64(_ADLER)
    for block in range(blocks):
        g = image * blocks + block
        info[g, _START] = at
        if info[g, _KIND] == wp.int64(_STORED):
            at = ((at + wp.int64(3) + wp.int64(7)) >> wp.int64(3)) << wp.int64(3)
            at += wp.int64(32)
        else:
            at += info[g, _HEADER_BITS]
        at += info[g, _DATA_BITS]
        a = (a + info[g, _SUM_A]) % wp.int64(_ADLER)
        b = (b + info[g, _SUM_B]) % wp.int64(_ADLER)
    streams[image, 0] = (at + wp.int64(7)) >> wp.int64(3)
    streams[image, 1] = (b << wp.int64(16)) | a


@wp.func
def _add_bits(out: wp.array2d(dtype=wp.uint32), image: int, at: wp.int64, value: wp.uint64,
              bits: int):
    """``bits`` (at most 32) bits of ``value`` added into the image's words at bit ``at``."""
    word = int(at >> wp.int64(5))
    shift = wp.uint64(at & wp.int64(31))
    v = value << shift
    wp.atomic_add(out, image, word, wp.uint32(v & wp.uint64(0xFFFFFFFF)))
    if int(shift) + bits > 32:
        wp.atomic_add(out, image, word + 1, wp.uint32(v >> wp.uint64(32)))


@wp.kernel
def write_kernel(codes: wp.array(dtype=wp.uint8), pixels: int, stride: int, channels: int,
                 total: int, blocks: int, info: wp.array2d(dtype=wp.int64),
                 code: wp.array2d(dtype=wp.int32), lengths: wp.array2d(dtype=wp.int32),
                 fixed: wp.array2d(dtype=wp.int32), offsets: wp.array2d(dtype=wp.int32),
                 header: wp.array2d(dtype=wp.uint32), out: wp.array2d(dtype=wp.uint32)):
    """Each segment's codes into the image's zeroed words, and each block's header.

    The thread past a block's segments writes its header bits, stored lengths and
    end-of-block code.
    """
    image, block, segment = wp.tid()
    g = image * blocks + block
    kind = int(info[g, _KIND])
    start = info[g, _START]
    data = start + info[g, _HEADER_BITS]
    if kind == _STORED:
        data = ((start + wp.int64(10)) >> wp.int64(3)) << wp.int64(3)
        data += wp.int64(32)
    if segment == SEGMENTS:
        for w in range((int(info[g, _HEADER_BITS]) + 31) / 32):
            left = int(info[g, _HEADER_BITS]) - 32 * w
            _add_bits(out, image, start + wp.int64(32 * w), wp.uint64(header[g, w]),
                      wp.min(left, 32))
        if kind == _STORED:
            stored = wp.min(BLOCK, total - block * BLOCK)
            field = wp.uint64(stored) | (wp.uint64(stored ^ 0xFFFF) << wp.uint64(16))
            _add_bits(out, image, data - wp.int64(32), field, 32)  # LEN, NLEN
        else:
            end_code = int(info[g, _END_CODE])
            eob = _code_of(kind, 256, g, g * TREES, code, lengths, fixed)
            _add_bits(out, image, data + info[g, _DATA_BITS] - wp.int64(end_code),
                      wp.uint64(eob[0]), end_code)
        return
    first = block * BLOCK + segment * SEGMENT
    last = wp.min(wp.min(first + SEGMENT, (block + 1) * BLOCK), total)
    at = data + wp.int64(offsets[g, segment])
    held = wp.uint64(0)  # bits not yet added, from bit ``at`` on
    n = wp.int32(0)
    for i in range(first, last):
        value = _literal(codes, image * pixels, i, stride, channels)
        c = _code_of(kind, value, g, g * TREES, code, lengths, fixed)
        held = held | (wp.uint64(c[0]) << wp.uint64(n))
        n += c[1]
        if n >= 32:
            _add_bits(out, image, at, held & wp.uint64(0xFFFFFFFF), 32)
            at += wp.int64(32)
            held = held >> wp.uint64(32)
            n -= 32
    if n > 0:
        _add_bits(out, image, at, held, n)
