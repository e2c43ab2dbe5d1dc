"""Image payloads to arrays, and left/right pairing by stamp (pure: no DDS)."""

from __future__ import annotations

import numpy as np
import pytest

from inhand_stereo.image_encoding import ImageError, image_to_array, to_grey, to_rgb
from inhand_stereo.stereo_pairing import PairBuffer


def test_rgb_bgr_and_mono_decode_with_padded_rows():
    rng = np.random.default_rng(1)
    rgb = rng.integers(0, 256, (4, 5, 3), dtype=np.uint8)
    padded = np.zeros((4, 20), np.uint8)          # step 20 > 5 * 3: row padding
    padded[:, :15] = rgb.reshape(4, 15)
    decoded = image_to_array('rgb8', 4, 5, 20, padded.tobytes())
    assert np.array_equal(decoded, rgb)
    bgr = image_to_array('bgr8', 4, 5, 20, padded.tobytes())
    assert np.array_equal(to_rgb(bgr, 'bgr8'), rgb[:, :, ::-1])
    mono = image_to_array('mono8', 4, 15, 20, padded.tobytes())
    assert mono.shape == (4, 15) and np.array_equal(to_grey(mono, 'mono8'), mono)
    assert np.array_equal(to_rgb(mono, 'mono8'), np.repeat(mono[:, :, None], 3, axis=2))


def test_grey_of_rgb_and_bgr_agree():
    rng = np.random.default_rng(2)
    rgb = rng.integers(0, 256, (6, 7, 3), dtype=np.uint8)
    assert np.array_equal(to_grey(rgb, 'rgb8'), to_grey(np.ascontiguousarray(rgb[:, :, ::-1]),
                                                          'bgr8'))


def test_mono16_keeps_the_high_byte_in_either_byte_order():
    values = np.array([[0x1234, 0xff00]], dtype='<u2')
    assert image_to_array('mono16', 1, 2, 4, values.tobytes()).tolist() == [[0x12, 0xff]]
    assert image_to_array('mono16', 1, 2, 4, values.astype('>u2').tobytes(),
                          is_bigendian=True).tolist() == [[0x12, 0xff]]


@pytest.mark.parametrize('arguments, message', [
    (('bayer_rggb8', 2, 2, 2, bytes(4)), "unsupported image encoding 'bayer_rggb8'"),
    (('rgb8', 2, 2, 5, bytes(10)), 'step 5 is shorter than a row'),
    (('rgb8', 2, 2, 6, bytes(11)), 'holds 11 bytes, 12 expected'),
    (('mono8', 0, 2, 2, b''), 'image size 2x0 is empty'),
])
def test_bad_images_are_refused_with_the_reason(arguments, message):
    with pytest.raises(ImageError, match=message):
        image_to_array(*arguments)


def test_pairs_by_exact_stamp_in_either_order_and_counts_lost_halves():
    buffer: PairBuffer[str] = PairBuffer(depth=2)
    assert buffer.add('left', 100, 'L100') is None
    assert buffer.add('right', 100, 'R100') == (100, 'L100', 'R100')
    assert buffer.add('right', 200, 'R200') is None
    assert buffer.add('left', 200, 'L200') == (200, 'L200', 'R200')
    # the right image of 300 is lost; 400 pairs and the orphan left of 300 is dropped
    assert buffer.add('left', 300, 'L300') is None
    assert buffer.add('left', 400, 'L400') is None
    assert buffer.add('right', 400, 'R400') == (400, 'L400', 'R400')
    assert (buffer.paired, buffer.dropped, buffer.waiting) == (3, 1, 0)
    # more unpaired halves than the depth: the oldest go
    for stamp in (500, 600, 700):
        buffer.add('right', stamp, f'R{stamp}')
    assert buffer.waiting == 2 and buffer.dropped == 2
    with pytest.raises(ValueError):
        buffer.add('middle', 1, 'x')
