"""Decoding the WebP images of DeMoN's files, by one of `IMAGE_DECODERS`.

`demon` (the default) is libwebp with `bypass_filtering` and `no_fancy_upsampling`, as
DeMoN's C++ reader op that its networks were trained and evaluated with, through the
`webp` package (a dependency of gld); `opencv` is libwebp's default decoding, as DeMoN's
Python `view_io` reader: an approximation of DeMoN's images, asked for by name. The two
differ on lossy WebP only (DeMoN's files: by a few grey levels on most pixels); lossless
WebP decodes to the same pixels either way, so `demon` reads lossless images even without
the `webp` package and refuses a lossy one (`MissingDecoderError`) rather than
approximate it. Whether an image is lossy is read from its RIFF chunks
(`webp_compression`), without decoding it.
"""

from __future__ import annotations

import cv2
import numpy as np

from data.demon.damage import DamagedDataError
from gld.arguments import ArgumentError

# "demon": as DeMoN's C++ reader op; "opencv": libwebp's default decoding (module docstring).
IMAGE_DECODERS = ("demon", "opencv")
DEFAULT_IMAGE_DECODER = "demon"


class MissingDecoderError(ArgumentError, ImportError):
    """DeMoN's WebP decoding is asked for (the default) and a lossy image needs the
    `webp` package, which is not installed (or not of the layout it relies on)."""


def webp_decoder_available() -> bool:
    """Whether the `webp` package (libwebp bindings), which the `demon` image decoder
    needs for lossy images, is installed and has the decoder-options layout it relies on."""
    try:
        import webp
    except ImportError:
        return False
    # `webp` declares only `use_threads` of libwebp's WebPDecoderOptions, but allocates
    # the whole struct; its layout (decode.h) puts bypass_filtering and
    # no_fancy_upsampling at ints 0 and 1 and use_threads at int 10.
    return webp.ffi.offsetof("WebPDecoderOptions", "use_threads") == 10 * webp.ffi.sizeof("int")


def resolve_image_decoder(decoder: str | None) -> str:
    """An `IMAGE_DECODERS` name; None is `DEFAULT_IMAGE_DECODER` ("demon"). The default
    does not depend on what is installed, so the same build options give the same
    records everywhere: without the `webp` package a lossy image is refused, not decoded
    otherwise (`reader.check_image_decoder`)."""
    if decoder is None:
        return DEFAULT_IMAGE_DECODER
    if decoder not in IMAGE_DECODERS:
        raise ValueError(f"unknown image decoder {decoder!r}; valid: {IMAGE_DECODERS}")
    return decoder


def missing_decoder_message(where: str) -> str:
    """The one line that refuses to approximate DeMoN's decoding of `where`'s images."""
    return (
        f"DeMoN's WebP decoding (image_decoder=demon, the default) needs the `webp` package "
        f"for the lossy images of {where}: pip install webp (a dependency of gld, which "
        f"pip install -e . installs), or build with --image_decoder=opencv (python -m "
        f"data.build; image_decoder='opencv' in data.prepare) to accept OpenCV's decoding, "
        f"a few grey levels off DeMoN's"
    )


def webp_compression(data: bytes) -> str | None:
    """How WebP bytes are compressed: "lossless" (VP8L only), "lossy" (a VP8 bitstream) or
    None (no WebP container), from the RIFF chunk names alone: nothing is decoded."""
    if len(data) < 16 or data[:4] != b"RIFF" or data[8:12] != b"WEBP":
        return None
    chunks, offset = set(), 12
    while offset + 8 <= len(data):
        chunks.add(bytes(data[offset : offset + 4]))
        size = int.from_bytes(data[offset + 4 : offset + 8], "little")
        offset += 8 + size + (size & 1)  # chunks are padded to an even size
    if b"VP8 " in chunks:
        return "lossy"
    return "lossless" if b"VP8L" in chunks else None


def decode_webp_libwebp(
    data: bytes, *, bypass_filtering: bool = True, no_fancy_upsampling: bool = True
) -> np.ndarray | None:
    """WebP bytes -> [H, W, 3] uint8 RGB by libwebp's advanced API (the `webp` package).

    With both options on (the default) this is DeMoN's C++ reader op's decoding; with
    both off it is libwebp's default, which OpenCV uses. Returns None if undecodable.
    """
    import webp

    ffi, lib = webp.ffi, webp.lib
    buffer = ffi.from_buffer(data)
    config = ffi.new("WebPDecoderConfig*")
    if not lib.WebPInitDecoderConfig(config):
        raise RuntimeError("libwebp: WebPInitDecoderConfig failed (version mismatch)")
    if lib.WebPGetFeatures(buffer, len(data), ffi.addressof(config, "input")) != 0:
        return None
    options = ffi.cast("int *", ffi.addressof(config, "options"))
    options[0], options[1] = int(bypass_filtering), int(no_fancy_upsampling)
    height, width = config.input.height, config.input.width
    image = np.empty((height, width, 3), np.uint8)
    config.output.colorspace = webp.WebPColorMode.RGB.value
    config.output.u.RGBA.rgba = ffi.cast("uint8_t *", ffi.from_buffer(image))
    config.output.u.RGBA.stride = 3 * width
    config.output.u.RGBA.size = image.size
    config.output.is_external_memory = 1
    status = lib.WebPDecode(buffer, len(data), config)
    lib.WebPFreeDecBuffer(ffi.addressof(config, "output"))
    return image if status == 0 else None


def _decode_opencv(data: bytes) -> np.ndarray | None:
    """Bytes -> [H, W, 3] uint8 RGB by OpenCV (libwebp's defaults); None if undecodable."""
    image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_COLOR)
    return None if image is None else cv2.cvtColor(image, cv2.COLOR_BGR2RGB)


def decode_image(
    data: bytes, where: str = "image", decoder: str = DEFAULT_IMAGE_DECODER
) -> np.ndarray:
    """WebP (or any OpenCV-readable) bytes -> [H, W, 3] uint8 RGB.

    Args:
      data: the encoded bytes.
      where: names the dataset in errors.
      decoder: one of `IMAGE_DECODERS` (see the module docstring).

    Raises:
      DamagedDataError (`corrupt_image`): undecodable bytes.
      MissingDecoderError: a decodable lossy image, `demon` asked for, no `webp` package.
    """
    # Lossless WebP decodes to the same pixels whichever libwebp options are set.
    if decoder == "demon" and webp_compression(data) != "lossless":
        if webp_decoder_available():
            image = decode_webp_libwebp(data)
        elif _decode_opencv(data) is not None:
            raise MissingDecoderError(missing_decoder_message(where))
        else:
            image = None  # damaged, whichever the decoder
    else:
        image = _decode_opencv(data)
    if image is None:
        raise DamagedDataError("corrupt_image", where, f"undecodable image ({len(data)} bytes)")
    return image
