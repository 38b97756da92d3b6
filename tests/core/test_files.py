"""The PNG encoder: every image kind the suite writes reads back exactly through OpenCV and
Pillow, and anything else is refused naming what was expected."""

import io

import cv2
import numpy as np
import pytest
from PIL import Image

from stereo_bench.core.files import encode_png


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
@pytest.mark.parametrize("shape", [(7, 5), (7, 5, 1), (7, 5, 3), (7, 5, 4), (1, 1), (300, 411)])
def test_png_reads_back_exactly(shape, dtype):
    image = np.random.default_rng(3).integers(0, np.iinfo(dtype).max + 1, size=shape,
                                              dtype=dtype)
    png = encode_png(image)
    back = cv2.imdecode(np.frombuffer(png, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.dtype == dtype
    np.testing.assert_array_equal(back, image.reshape(back.shape))
    # Pillow reads the channels in file order: RGB(A), the reverse of OpenCV's BGR(A).
    pil = Image.open(io.BytesIO(png))
    pil.load()
    assert pil.size == (shape[1], shape[0])
    if dtype == np.uint8:
        rgb = np.asarray(pil)
        expected = image.reshape(rgb.shape) if len(shape) == 2 or shape[2] == 1 \
            else image[..., [2, 1, 0, 3][:shape[2]]]
        np.testing.assert_array_equal(rgb, expected)


@pytest.mark.parametrize("image", [np.zeros((4, 4), np.float32), np.zeros((4, 4, 2), np.uint8),
                                   np.zeros((0, 4), np.uint8), np.zeros(4, np.uint8)])
def test_png_refuses_what_it_cannot_write(image):
    with pytest.raises(ValueError, match="expected a non-empty 8- or 16-bit image"):
        encode_png(image)
