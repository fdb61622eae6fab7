"""Per-image draws keyed by a frame sequence (issue 38): counter word 1 says what the index
numbers, so a sequence's draws never meet a sample's and a sample's are those of before."""

import numpy as np
import pytest

from gpu_blur.reference import rng
from gpu_blur.reference.rng import Keyed, Stream

SEED = 0x0123456789ABCDEF


def expected(index, stream, count, word1):
    """The documented layout: element i is word i % 4 of (i // 4, word1, index, stream << 24)."""
    blocks = -(-count // 4)
    counter = np.array([[b, word1, index, int(stream) << 24] for b in range(blocks)],
                       dtype=np.uint32)
    bits = rng.philox4x32(counter, rng.key_from_seed(SEED)).reshape(-1)[:count]
    return rng.uniform_from_bits(bits)


@pytest.mark.parametrize("count", [3, 10, 40])  # the Python-int path and numpy's
@pytest.mark.parametrize("stream", [Stream.PARAMS, Stream.TRAJECTORY, Stream.KERNEL])
def test_a_sequence_s_draws_have_word_one_set_and_a_sample_s_keep_the_old_counters(stream,
                                                                                   count):
    sample = rng.image_uniforms(SEED, 7, stream, count)
    np.testing.assert_array_equal(sample, expected(7, stream, count, 0))
    np.testing.assert_array_equal(rng.image_uniforms(SEED, 7, stream, count, Keyed.SAMPLE),
                                  sample)
    sequence = rng.image_uniforms(SEED, 7, stream, count, Keyed.SEQUENCE)
    np.testing.assert_array_equal(sequence, expected(7, stream, count, 1))
    assert not np.any(sequence == sample)


@pytest.mark.parametrize("count", [3, 40])
def test_a_batch_of_sequences_draws_row_by_row_what_one_sequence_draws(count):
    indices = [0, 3, 3, 9, 2**32 - 1]
    batch = rng.image_uniforms_batch(SEED, indices, Stream.PARAMS, count, Keyed.SEQUENCE)
    for row, index in zip(batch, indices, strict=True):
        np.testing.assert_array_equal(
            row, rng.image_uniforms(SEED, index, Stream.PARAMS, count, Keyed.SEQUENCE))
    np.testing.assert_array_equal(batch[1], batch[2])


def test_what_the_index_numbers_is_checked():
    with pytest.raises(ValueError, match="keyed must be a gpu_blur.reference.rng.Keyed"):
        rng.image_uniforms(SEED, 0, Stream.PARAMS, 4, 2)
    with pytest.raises(ValueError, match="keyed must be"):
        rng.image_uniforms_batch(SEED, [0, 1], Stream.PARAMS, 40, 5)
