"""Tests of diffcam.io: reading captures and the preprocessing steps."""

import warnings

import h5py
import numpy as np
import pytest
import scipy.io
import tifffile
from PIL import Image

from diffcam.core.errors import DiffcamError, ShapeError
from diffcam.io import (BackgroundWarning, dark_level, downsample, normalise_l2,
                        read_image, read_mat_stack, read_psf_stack, saturation_mask,
                        subtract_background)


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.mark.parametrize("dtype", [np.uint8, np.uint16])
def test_png_gray_8_and_16_bit(tmp_path, rng, dtype):
    data = rng.integers(0, np.iinfo(dtype).max, (12, 17), dtype=dtype)
    Image.fromarray(data).save(tmp_path / "a.png")
    cap = read_image(tmp_path / "a.png")
    assert cap.image.dtype == np.float32 and cap.channels is None
    np.testing.assert_array_equal(cap.image, data)
    assert cap.full_scale == np.iinfo(dtype).max


def test_png_rgb_channels_first(tmp_path, rng):
    data = rng.integers(0, 255, (6, 7, 3), dtype=np.uint8)
    Image.fromarray(data).save(tmp_path / "c.png")
    cap = read_image(tmp_path / "c.png")
    assert cap.channels == ("R", "G", "B") and cap.image.shape == (3, 6, 7)
    np.testing.assert_array_equal(cap.image[2], data[..., 2])


def test_tiff_16_bit_and_stack(tmp_path, rng):
    data = rng.integers(0, 65535, (9, 10), dtype=np.uint16)
    tifffile.imwrite(tmp_path / "a.tif", data)
    np.testing.assert_array_equal(read_image(tmp_path / "a.tif").image, data)
    planes = rng.random((3, 5, 6)).astype(np.float32)
    for k, p in enumerate(planes):
        tifffile.imwrite(tmp_path / f"psf{k:02d}.tiff", p)
    stack = read_psf_stack(sorted(tmp_path.glob("psf*.tiff")))
    np.testing.assert_array_equal(stack, planes)


def test_npy_bgr_needs_channel_order(tmp_path, rng):
    data = rng.random((5, 8, 3)).astype(np.float32)
    np.save(tmp_path / "x.npy", data)
    with pytest.raises(DiffcamError, match="channel_order='BGR'"):
        read_image(tmp_path / "x.npy")
    cap = read_image(tmp_path / "x.npy", channel_order="BGR")
    assert cap.channels == ("B", "G", "R") and cap.full_scale is None
    np.testing.assert_array_equal(cap.image[0], data[..., 0])


def test_mat_v5_and_v73(tmp_path, rng):
    """(y, x, z) MATLAB stacks come back as (z, y, x) from both file versions."""
    stack_yxz = rng.random((6, 7, 4))
    scipy.io.savemat(tmp_path / "v5.mat", {"psf": stack_yxz})
    np.testing.assert_allclose(read_mat_stack(tmp_path / "v5.mat"),
                               np.moveaxis(stack_yxz, -1, 0), rtol=1e-6)
    # v7.3 is HDF5 with MATLAB's column-major layout: h5py sees the axes reversed
    with h5py.File(tmp_path / "v73.mat", "w") as f:
        f.create_dataset("psf", data=np.transpose(stack_yxz))
        f.create_dataset("other", data=np.zeros(2))
    with pytest.raises(DiffcamError, match="say which one"):
        read_mat_stack(tmp_path / "v73.mat")
    np.testing.assert_allclose(read_mat_stack(tmp_path / "v73.mat", key="psf"),
                               np.moveaxis(stack_yxz, -1, 0), rtol=1e-6)


def test_bad_files(tmp_path, rng):
    (tmp_path / "empty.png").write_bytes(b"")
    with pytest.raises(DiffcamError, match="empty"):
        read_image(tmp_path / "empty.png")
    data = rng.integers(0, 255, (20, 20), dtype=np.uint8)
    Image.fromarray(data).save(tmp_path / "ok.png")
    raw = (tmp_path / "ok.png").read_bytes()
    (tmp_path / "cut.png").write_bytes(raw[:60])
    with pytest.raises(DiffcamError, match="corrupt|truncated"):
        read_image(tmp_path / "cut.png")
    (tmp_path / "fake.tif").write_bytes(b"not a tiff at all" * 10)
    with pytest.raises(DiffcamError, match="could not be read"):
        read_image(tmp_path / "fake.tif")
    with pytest.raises(DiffcamError, match="no such file"):
        read_image(tmp_path / "missing.png")
    with pytest.raises(DiffcamError, match="unsupported"):
        read_image(tmp_path / "x.jpg")
    bad = np.ones((4, 4), np.float32)
    bad[1, 1] = np.nan
    np.save(tmp_path / "nan.npy", bad)
    with pytest.raises(DiffcamError, match="NaN/Inf"):
        read_image(tmp_path / "nan.npy")
    np.save(tmp_path / "e.npy", np.zeros((0, 3)))
    with pytest.raises(DiffcamError, match="empty"):
        read_image(tmp_path / "e.npy")
    (tmp_path / "bad.mat").write_bytes(b"MATLAB 5.0 garbage" * 3)
    with pytest.raises(DiffcamError):
        read_mat_stack(tmp_path / "bad.mat")
    tifffile.imwrite(tmp_path / "a.tiff", np.ones((4, 4), np.float32))
    tifffile.imwrite(tmp_path / "b.tiff", np.ones((4, 5), np.float32))
    with pytest.raises(ShapeError, match="one shape"):
        read_psf_stack([tmp_path / "a.tiff", tmp_path / "b.tiff"])


def test_sixteen_bit_colour_png_is_refused(tmp_path):
    # a minimal 16-bit RGB PNG header is enough: the check reads IHDR before decoding
    import struct
    import zlib
    ihdr = struct.pack(">IIBBBBB", 1, 1, 16, 2, 0, 0, 0)
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(  # noqa: E731
        ">I", zlib.crc32(t + d))
    png = (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr)
           + chunk(b"IDAT", zlib.compress(b"\x00" + b"\x00" * 6)) + chunk(b"IEND", b""))
    (tmp_path / "rgb16.png").write_bytes(png)
    with pytest.raises(DiffcamError, match="16-bit colour PNG"):
        read_image(tmp_path / "rgb16.png")


def test_background_subtraction():
    image = np.full((10, 10), 100.0, np.float32)
    image[4:6, 4:6] = 1000
    image[0, 0] = 97  # noise below the bias
    with pytest.warns(BackgroundWarning, match="clipped 1"):
        out = subtract_background(image, 100)
    assert out.min() == 0 and out.max() == 900
    with pytest.raises(DiffcamError, match="background is too large"):
        subtract_background(image, 500)
    frame = np.full_like(image, 10)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert subtract_background(image, frame).min() == 87
    colour = np.stack([image, 2 * image])
    level = dark_level(colour, (slice(7, 10), slice(7, 10)))
    np.testing.assert_allclose(level, [100, 200])
    with pytest.warns(BackgroundWarning):
        per_channel = subtract_background(colour, level)
    assert per_channel.shape == colour.shape and per_channel.min() == 0
    with pytest.raises(ShapeError, match="does not match"):
        subtract_background(image, np.ones((3, 3)))


def test_saturation_mask(tmp_path):
    data = np.zeros((4, 4), np.uint16)
    data[1, 1] = 65520   # a 12-bit sensor's full scale in a 16-bit file
    data[2, 2] = 65535
    data[3, 3] = 60000
    tifffile.imwrite(tmp_path / "s.tif", data)
    mask = saturation_mask(read_image(tmp_path / "s.tif"))
    assert mask.sum() == 2 and mask[1, 1] and mask[2, 2]
    np.save(tmp_path / "f.npy", data.astype(np.float32))
    with pytest.raises(DiffcamError, match="level"):
        saturation_mask(read_image(tmp_path / "f.npy"))


def test_downsample_and_normalise():
    image = np.arange(36, dtype=np.float32).reshape(6, 6)
    np.testing.assert_allclose(downsample(image, 2)[0, 0], (0 + 1 + 6 + 7) / 4)
    assert downsample(np.ones((3, 7, 9)), 2).shape == (3, 3, 4)
    with pytest.raises(DiffcamError, match="positive integer"):
        downsample(image, 0)
    n = normalise_l2(np.stack([image, 3 * image]))
    np.testing.assert_allclose(np.sqrt((n ** 2).sum(axis=(-2, -1))), 1, rtol=1e-6)
    with pytest.raises(DiffcamError, match="all-zero"):
        normalise_l2(np.zeros((3, 3)))
