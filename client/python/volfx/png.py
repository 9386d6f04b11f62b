"""PNG reading and writing for frame comparisons, standard library only (zlib and struct).

``read(data)`` decodes a non-interlaced PNG of 8-bit samples (grey, grey+alpha, RGB, RGBA or
palette) into an ``Image`` of RGBA bytes; ``write(image)`` encodes an ``Image`` as an RGBA PNG.
Anything else (16-bit samples, interlacing, a damaged stream) raises ``PngError`` saying what.
"""

import struct
import zlib

SIGNATURE = b"\x89PNG\r\n\x1a\n"

# Colour type -> samples per pixel, for 8-bit images.
_CHANNELS = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}


class PngError(ValueError):
    """The bytes are not a PNG this module reads."""


class Image:
    """``width`` x ``height`` pixels as RGBA bytes, row after row from the top."""

    def __init__(self, width, height, rgba):
        if len(rgba) != width * height * 4:
            raise ValueError("%dx%d RGBA needs %d bytes, got %d" %
                             (width, height, width * height * 4, len(rgba)))
        self.width = width
        self.height = height
        self.rgba = bytes(rgba)

    @property
    def size(self):
        return self.width, self.height

    def pixel(self, x, y):
        i = 4 * (y * self.width + x)
        return tuple(self.rgba[i:i + 4])


def _chunks(data):
    pos = len(SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        body = data[pos + 8:pos + 8 + length]
        if len(body) != length or pos + 12 + length > len(data):
            raise PngError("the %s chunk is cut short" % kind.decode("latin-1"))
        (crc,) = struct.unpack(">I", data[pos + 8 + length:pos + 12 + length])
        if zlib.crc32(kind + body) != crc:
            raise PngError("the %s chunk's CRC does not match" % kind.decode("latin-1"))
        yield kind, body
        pos += 12 + length


def _unfilter(raw, width, height, bpp):
    """Undoes the per-row filters (types 0-4) of 'raw'; returns the rows joined."""
    stride = width * bpp
    out = bytearray(stride * height)
    prev = bytearray(stride)
    pos = 0
    for y in range(height):
        if pos + 1 + stride > len(raw):
            raise PngError("the image data is cut short at row %d" % y)
        kind = raw[pos]
        row = bytearray(raw[pos + 1:pos + 1 + stride])
        pos += 1 + stride
        if kind == 1:
            for i in range(bpp, stride):
                row[i] = (row[i] + row[i - bpp]) & 255
        elif kind == 2:
            for i in range(stride):
                row[i] = (row[i] + prev[i]) & 255
        elif kind == 3:
            for i in range(stride):
                left = row[i - bpp] if i >= bpp else 0
                row[i] = (row[i] + ((left + prev[i]) >> 1)) & 255
        elif kind == 4:
            for i in range(stride):
                a = row[i - bpp] if i >= bpp else 0
                b = prev[i]
                c = prev[i - bpp] if i >= bpp else 0
                p = a + b - c
                pa, pb, pc = abs(p - a), abs(p - b), abs(p - c)
                pred = a if pa <= pb and pa <= pc else (b if pb <= pc else c)
                row[i] = (row[i] + pred) & 255
        elif kind != 0:
            raise PngError("unknown filter type %d at row %d" % (kind, y))
        out[y * stride:(y + 1) * stride] = row
        prev = row
    return out


def read(data):
    """Decodes PNG bytes into an ``Image`` (RGBA)."""
    data = bytes(data)
    if not data.startswith(SIGNATURE):
        raise PngError("not a PNG (no PNG signature)")
    header, palette, alpha, idat = None, None, None, []
    for kind, body in _chunks(data):
        if kind == b"IHDR":
            header = struct.unpack(">IIBBBBB", body)
        elif kind == b"PLTE":
            palette = body
        elif kind == b"tRNS":
            alpha = body
        elif kind == b"IDAT":
            idat.append(body)
        elif kind == b"IEND":
            break
    if header is None:
        raise PngError("no IHDR chunk")
    width, height, depth, colour, _, _, interlace = header
    if depth != 8 or colour not in _CHANNELS:
        raise PngError("only 8-bit grey, RGB, palette, grey+alpha and RGBA PNGs are read "
                       "(bit depth %d, colour type %d)" % (depth, colour))
    if interlace:
        raise PngError("interlaced PNGs are not read")
    if colour == 3 and palette is None:
        raise PngError("a palette image without a PLTE chunk")
    try:
        raw = zlib.decompress(b"".join(idat))
    except zlib.error as e:
        raise PngError("the image data does not inflate: %s" % e) from None
    n = _CHANNELS[colour]
    px = _unfilter(raw, width, height, n)
    if colour == 6:
        return Image(width, height, px)
    rgba = bytearray(width * height * 4)
    if colour == 2:
        rgba[0::4], rgba[1::4], rgba[2::4] = px[0::3], px[1::3], px[2::3]
        rgba[3::4] = b"\xff" * (width * height)
    elif colour in (0, 4):
        for c in range(3):
            rgba[c::4] = px[0::n]
        rgba[3::4] = px[1::2] if colour == 4 else b"\xff" * (width * height)
    else:
        entries = [tuple(palette[3 * i:3 * i + 3]) + ((alpha[i] if alpha and i < len(alpha)
                                                       else 255),)
                   for i in range(len(palette) // 3)]
        for i, index in enumerate(px):
            if index >= len(entries):
                raise PngError("palette index %d past the palette's %d entries" %
                               (index, len(entries)))
            rgba[4 * i:4 * i + 4] = bytes(entries[index])
    return Image(width, height, rgba)


def read_file(path):
    with open(path, "rb") as f:
        return read(f.read())


def _chunk(kind, body):
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def write(image):
    """Encodes an ``Image`` as an 8-bit RGBA PNG; returns the bytes."""
    stride = image.width * 4
    raw = b"".join(b"\x00" + image.rgba[y * stride:(y + 1) * stride]
                   for y in range(image.height))
    return (SIGNATURE +
            _chunk(b"IHDR", struct.pack(">IIBBBBB", image.width, image.height, 8, 6, 0, 0, 0)) +
            _chunk(b"IDAT", zlib.compress(raw, 6)) + _chunk(b"IEND", b""))


def write_file(path, image):
    with open(path, "wb") as f:
        f.write(write(image))
