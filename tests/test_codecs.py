"""Streaming codecs: round trips (PNG checked with OpenImageIO), H.264 access units, odd sizes, bad input, bench."""

import json

import numpy as np
import OpenImageIO as oiio
import pytest

from render_core.errors import BlendsplatError, CodecError, FrameError, ShapeError
from render_core.evaluation.metrics import psnr  # uint8 images: over 0..255
from render_core.media.codecs import CODECS, H264Decoder, decode_image, h264_crf, make_encoder
from render_core.tools.cli import main


def smooth(h, w, t=0.0):
    """A smooth moving RGBA pattern; alpha varies too."""
    y, x = np.mgrid[0:h, 0:w].astype(np.float32)
    u, v = (x + 3 * t) / max(w, 64), (y + 2 * t) / max(h, 64)
    rgba = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * u), 0.5 + 0.4 * np.cos(2 * np.pi * v),
                     0.5 + 0.3 * np.sin(2 * np.pi * (u + v)), np.clip(u * v * 1.2, 0, 1)], -1)
    return np.ascontiguousarray(np.round(rgba * 255).astype(np.uint8))


def noise(h, w, seed=0):
    return np.random.default_rng(seed).integers(0, 256, (h, w, 4), dtype=np.uint8)


def nal_types(data):
    """NAL unit types of an Annex B byte stream."""
    types, i = [], data.find(b"\x00\x00\x01")
    while i >= 0:
        types.append(data[i + 3] & 0x1F)
        i = data.find(b"\x00\x00\x01", i + 3)
    return types


def oiio_read(path):
    config = oiio.ImageSpec()
    config.attribute("oiio:UnassociatedAlpha", 1)  # as stored: OIIO premultiplies PNG colour by alpha by default
    inp = oiio.ImageInput.open(str(path), config)
    assert inp is not None, oiio.geterror()
    try:
        assert inp.spec().nchannels == 4 and inp.spec().format == oiio.TypeDesc("uint8")
        return inp.read_image(0, 0, 0, 4, oiio.UINT8)
    finally:
        inp.close()


def test_media_types():
    for codec, media in zip(CODECS, ("image/jpeg", "image/png", "application/octet-stream", "video/h264"),
                            strict=True):
        with make_encoder(codec, 16, 16) as enc:
            assert (enc.codec, enc.media_type) == (codec, media)


@pytest.mark.parametrize("h, w", [(48, 64), (33, 17), (1, 1)])
def test_raw_i420_is_the_4_2_0_conversion_of_the_frame_in_y_u_v_order_and_no_stream_codec(h, w):
    """The frame format the WebRTC track takes: make_encoder makes it, but it is no codec of the API."""
    from render_core.media.pixels import rgba8_to_i420

    img = smooth(h, w)
    ch, cw = (h + 1) // 2, (w + 1) // 2
    planes = [np.zeros((h, w), np.uint8), np.zeros((ch, cw), np.uint8), np.zeros((ch, cw), np.uint8)]
    rgba8_to_i420(img, *planes)
    with make_encoder("raw_i420", w, h) as enc:
        assert (enc.codec, enc.media_type) == ("raw_i420", "application/octet-stream")
        data = enc.encode(img)
    assert isinstance(data, bytes) and data == b"".join(p.tobytes() for p in planes)
    assert "raw_i420" not in CODECS
    with pytest.raises(CodecError, match="unknown codec"):
        decode_image("raw_i420", data, w, h)


def test_jpeg_round_trip_and_quality():
    img = smooth(96, 128)
    enc = make_encoder("jpeg", 128, 96)
    data = enc.encode(img)
    assert data[:2] == b"\xff\xd8"
    out = decode_image("jpeg", data, 128, 96)
    assert out.shape == (96, 128, 3) and out.dtype == np.uint8
    assert psnr(out, img[..., :3]) >= 35
    low, high = (len(make_encoder("jpeg", 128, 96, quality=q).encode(img)) for q in (30, 95))
    assert low < high
    assert len(make_encoder("jpeg", 128, 96, quality=90).encode(img)) == len(data)  # 0 is 90


@pytest.mark.parametrize("h, w", [(64, 80), (33, 17), (1, 1)])
def test_png_is_bit_exact_with_alpha_through_oiio(tmp_path, h, w):
    enc = make_encoder("png", w, h)
    for i, img in enumerate((smooth(h, w), noise(h, w, seed=h))):  # noise exercises the filter's wrap-around
        data = enc.encode(img)
        path = tmp_path / f"{i}.png"
        path.write_bytes(data)
        np.testing.assert_array_equal(oiio_read(path), img)
        np.testing.assert_array_equal(decode_image("png", data, w, h), img)


def test_raw_rgba_is_exact():
    img = noise(33, 17)
    data = make_encoder("raw_rgba", 17, 33).encode(img)
    assert data == img.tobytes()
    np.testing.assert_array_equal(decode_image("raw_rgba", data, 17, 33), img)


def test_h264_one_access_unit_per_frame():
    w, h = 96, 64
    enc, dec = make_encoder("h264", w, h), H264Decoder()
    for i in range(10):
        img = smooth(h, w, t=i)
        data = enc.encode(img)
        assert data and data.startswith((b"\x00\x00\x00\x01", b"\x00\x00\x01"))
        types = nal_types(data)
        if i == 0:
            assert 5 in types and 7 in types and 8 in types, types
        else:
            assert 5 not in types, (i, types)
        out = dec.decode(data)
        assert out.shape == (h, w, 3) and out.dtype == np.uint8
        assert psnr(out, img[..., :3]) >= 30, i
    enc.close()
    with pytest.raises(RuntimeError):
        enc.encode(smooth(h, w))


def test_h264_keyframe_interval_and_quality():
    enc = make_encoder("h264", 32, 32, fps=2.0)  # GOP 2 * fps = 4 frames
    idr = [5 in nal_types(enc.encode(smooth(32, 32, t=i))) for i in range(9)]
    assert idr[0] and idr[4] and idr[8]
    assert (h264_crf(0), h264_crf(56), h264_crf(1), h264_crf(100)) == (23, 23, 51, 1)
    img = noise(32, 32)
    assert len(make_encoder("h264", 32, 32, quality=10).encode(img)) < len(
        make_encoder("h264", 32, 32, quality=90).encode(img))


@pytest.mark.parametrize("codec", CODECS)
def test_odd_sizes(codec):
    w, h = 17, 33
    enc = make_encoder(codec, w, h)
    if codec == "h264":
        dec = H264Decoder(w, h)
        for i in range(3):
            img = smooth(h, w, t=i)
            out = dec.decode(enc.encode(img))
            assert out.shape == (h, w, 3) and psnr(out, img[..., :3]) >= 30
        return
    img = smooth(h, w)
    out = decode_image(codec, enc.encode(img), w, h)
    if codec == "jpeg":
        assert out.shape == (h, w, 3) and psnr(out, img[..., :3]) >= 30
    else:
        np.testing.assert_array_equal(out, img)


@pytest.mark.parametrize("codec", (*CODECS, "raw_i420"))
def test_non_contiguous_input_is_copied(codec):
    img = smooth(32, 48)
    view = np.ascontiguousarray(img[::-1])[::-1]  # same pixels, negative strides
    assert not view.flags.c_contiguous
    a, b = make_encoder(codec, 48, 32), make_encoder(codec, 48, 32)
    assert a.encode(view) == b.encode(img)


@pytest.mark.parametrize("kwargs, field", [
    ({"codec": "webp"}, "codec"),
    ({"quality": 101}, "quality"),
    ({"quality": -1}, "quality"),
    ({"quality": 50.5}, "quality"),
    ({"width": 0}, "width"),
    ({"height": 2.0}, "height"),
    ({"fps": 0.0}, "fps"),
    ({"fps": float("nan")}, "fps"),
])
def test_bad_arguments_name_the_field(kwargs, field):
    args = {"codec": "jpeg", "width": 16, "height": 16, **kwargs}
    with pytest.raises(CodecError) as e:
        make_encoder(**args)
    assert e.value.field == field and str(e.value).startswith(f"{field}: ")
    # A codec setting is not a frame parameter: callers that map FrameError to a pose problem do not see it.
    assert isinstance(e.value, BlendsplatError) and not isinstance(e.value, FrameError)


@pytest.mark.parametrize("codec", (*CODECS, "raw_i420"))
@pytest.mark.parametrize("image", [
    np.zeros((16, 16, 4), np.float32),
    np.zeros((16, 16, 4), np.uint16),
    np.zeros((16, 16, 3), np.uint8),
    np.zeros((16, 17, 4), np.uint8),
    np.zeros((16, 16 * 4), np.uint8),
    [[[0, 0, 0, 0]] * 16] * 16,
])
def test_bad_images_raise_shape_error(codec, image):
    with make_encoder(codec, 16, 16) as enc, pytest.raises(ShapeError) as e:
        enc.encode(image)
    assert e.value.field == "image"


def test_bad_messages():
    with pytest.raises(ShapeError) as e:
        decode_image("raw_rgba", b"\x00" * 10, 2, 2)
    assert e.value.field == "data"
    with pytest.raises(ShapeError) as e:
        decode_image("png", make_encoder("png", 4, 4).encode(noise(4, 4)), 4, 5)
    assert e.value.field == "data"
    with pytest.raises(CodecError) as e:
        decode_image("h264", b"", 4, 4)
    assert e.value.field == "codec"
    for args, field in ((("webp", b"", 4, 4), "codec"), (("png", b"", 0, 4), "width")):
        with pytest.raises(CodecError) as e:
            decode_image(*args)
        assert e.value.field == field


def test_bench_codecs_json(capsys):
    assert main(["bench", "codecs", "--size", "64", "--frames", "2", "--gaussians", "2000", "--json"]) == 0
    report = json.loads(capsys.readouterr().out)
    assert report["size"] == 64 and report["frames"] == 2
    assert set(report["codecs"]) == set(CODECS)
    for codec, r in report["codecs"].items():
        assert 0 < r["encode_ms"]["median"] <= r["encode_ms"]["p95"], codec
        assert r["bytes_per_frame"] > 0 and r["mbit_s_at_30fps"] == pytest.approx(
            r["bytes_per_frame"] * 8 * 30 / 1e6, rel=1e-2)
    assert report["codecs"]["raw_rgba"]["bytes_per_frame"] == 64 * 64 * 4
