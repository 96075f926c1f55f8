"""Fiducial markers: families by name, their images, printable sheets, ChArUco boards.

Every family is one of ``cv2.aruco``'s predefined dictionaries, named as users know them:
``apriltag36h11`` (AprilTag 3's default), ``apriltag25h9``, ``apriltag16h5``,
``apriltag36h10``, ``aruco4x4_50`` ... ``aruco7x7_1000``, ``aruco-original``,
``arucomip36h12``.

Geometry is OpenCV's: a marker of side ``s`` has its corners at (-s/2, s/2, 0),
(s/2, s/2, 0), (s/2, -s/2, 0), (-s/2, -s/2, 0) (top-left first, clockwise in the image,
z out of the print), the order ``ArucoDetector`` returns them and
``SOLVEPNP_IPPE_SQUARE`` expects.  ``s`` is the side of the black square, quiet zone
excluded.

Sheets for printing (:func:`sheet`) are rendered at a given DPI so that a tag's printed
side is exact; :func:`write_png` records the DPI in the PNG (``pHYs``) and
:func:`write_pdf` places the sheet on an A4/Letter page at its physical size (print at
100 %, "actual size").
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from agent.errors import InvalidInputError
from services.camera.simulator import PlanarTarget

MM_PER_INCH = 25.4
PAGES_MM = {"a4": (210.0, 297.0), "letter": (215.9, 279.4)}


def families() -> dict[str, int]:
    """Family name -> ``cv2.aruco`` dictionary constant."""
    out = {}
    for attr in dir(cv2.aruco):
        if not attr.startswith("DICT_"):
            continue
        rest = attr[5:].lower()
        if rest.startswith("apriltag_"):
            name = "apriltag" + rest[9:]
        elif rest == "aruco_original":
            name = "aruco-original"
        elif rest.startswith("aruco_mip_"):
            name = "arucomip" + rest[10:]
        else:
            name = "aruco" + rest
        out[name] = getattr(cv2.aruco, attr)
    return out


def dictionary(family: str) -> cv2.aruco.Dictionary:
    """The ``cv2.aruco`` dictionary of ``family``; ``ValueError`` lists the known ones."""
    known = families()
    if family not in known:
        raise InvalidInputError(
            f"unknown marker family {family!r} (known: {', '.join(sorted(known))})")
    return cv2.aruco.getPredefinedDictionary(known[family])


def marker_corners(size_m: float) -> np.ndarray:
    """A marker's corners (4, 3) in its own frame, OpenCV's order."""
    s = size_m / 2
    return np.array([[-s, s, 0], [s, s, 0], [s, -s, 0], [-s, -s, 0]])


def marker_image(family: str, marker_id: int, module_px: int, quiet_modules: int = 1,
                 ) -> np.ndarray:
    """A marker's image (uint8), ``module_px`` pixels per bit cell, with a white quiet
    zone of ``quiet_modules`` cells around the black border."""
    d = dictionary(family)
    if not 0 <= marker_id < d.bytesList.shape[0]:
        raise InvalidInputError(f"{family} has ids 0..{d.bytesList.shape[0] - 1}, not {marker_id}")
    modules = d.markerSize + 2
    img = cv2.aruco.generateImageMarker(d, marker_id, modules * module_px, borderBits=1)
    q = quiet_modules * module_px
    return cv2.copyMakeBorder(img, q, q, q, q, cv2.BORDER_CONSTANT, value=255)


def marker_target(family: str, marker_id: int, size_m: float, module_px: int = 12,
                  ) -> PlanarTarget:
    """A printed marker of side ``size_m`` (with a one-cell quiet zone) for the simulator."""
    img = marker_image(family, marker_id, module_px)
    modules = dictionary(family).markerSize + 2
    side = size_m * (modules + 2) / modules
    return PlanarTarget(img, side, side)


def charuco_board(squares: tuple[int, int], square_m: float, marker_m: float,
                  family: str = "aruco4x4_50") -> cv2.aruco.CharucoBoard:
    """A ChArUco board of ``squares`` (columns, rows)."""
    if marker_m >= square_m:
        raise InvalidInputError(f"a ChArUco marker ({marker_m} m) must be smaller than its square "
                                f"({square_m} m)")
    return cv2.aruco.CharucoBoard(squares, square_m, marker_m, dictionary(family))


def board_target(board: cv2.aruco.CharucoBoard, px_per_square: int = 60) -> PlanarTarget:
    """A ChArUco board as a simulator target.  The target's frame (x right, y up, z out)
    is the board's own (OpenCV: origin at the top-left, y down, z into the board) turned
    by pi about x and moved to the board's centre; :func:`board_in_target` is that pose."""
    cols, rows = board.getChessboardSize()
    img = board.generateImage((cols * px_per_square, rows * px_per_square), marginSize=0)
    sq = board.getSquareLength()
    return PlanarTarget(img, cols * sq, rows * sq)


def board_in_target(board: cv2.aruco.CharucoBoard) -> np.ndarray:
    """The 4x4 pose of the board's OpenCV frame in its :func:`board_target`'s frame."""
    cols, rows = board.getChessboardSize()
    sq = board.getSquareLength()
    T = np.diag([1.0, -1.0, -1.0, 1.0])
    T[:3, 3] = (-cols * sq / 2, rows * sq / 2, 0)
    return T


def sheet(family: str, ids: list[int], size_m: float, dpi: float = 300.0,
          page: str = "a4", margin_mm: float = 10.0) -> np.ndarray:
    """A page (uint8, ``dpi``) of markers of side ``size_m``, each labelled with its
    family, id and size; ``ValueError`` if they do not fit."""
    if page not in PAGES_MM:
        raise InvalidInputError(f"page must be one of {', '.join(PAGES_MM)}")
    px_per_m = dpi / MM_PER_INCH * 1000.0
    modules = dictionary(family).markerSize + 2
    module_px = size_m * px_per_m / modules
    if module_px < 2:
        raise InvalidInputError(f"{size_m * 1000:g} mm tags at {dpi:g} dpi give {module_px:.1f} px "
                                "per cell: raise --dpi")
    w_mm, h_mm = PAGES_MM[page]
    page_px = (round(w_mm / MM_PER_INCH * dpi), round(h_mm / MM_PER_INCH * dpi))
    out = np.full((page_px[1], page_px[0]), 255, np.uint8)
    cell = round((modules + 2) * module_px)
    label = max(round(0.012 * px_per_m / 2), 12)
    margin = round(margin_mm / MM_PER_INCH * dpi)
    per_row = (page_px[0] - 2 * margin) // cell
    rows = (page_px[1] - 2 * margin) // (cell + label)
    if per_row * rows == 0:
        raise InvalidInputError(f"a {size_m * 1000:g} mm tag with its quiet zone does not fit on "
                                f"a {page} page")
    if per_row * rows < len(ids):
        raise InvalidInputError(f"{len(ids)} tags of {size_m * 1000:g} mm do not fit on one {page} "
                                f"page ({per_row * rows} do): print fewer ids per page")
    side = round(modules * module_px)
    for k, marker_id in enumerate(ids):
        r, c = divmod(k, per_row)
        x, y = margin + c * cell, margin + r * (cell + label)
        d = dictionary(family)
        img = cv2.aruco.generateImageMarker(d, marker_id, side, borderBits=1)
        q = (cell - side) // 2
        out[y + q:y + q + side, x + q:x + q + side] = img
        cv2.putText(out, f"{family} {marker_id}  {size_m * 1000:g} mm",
                    (x + q, y + cell + label // 2), cv2.FONT_HERSHEY_SIMPLEX,
                    label / 40.0, 0, max(1, label // 16), cv2.LINE_AA)
    return out


def write_png(path: str | Path, image: np.ndarray, dpi: float) -> Path:
    """Write a PNG that carries its DPI (a ``pHYs`` chunk after ``IHDR``), so image
    viewers print it at its physical size."""
    ok, buf = cv2.imencode(".png", image)
    if not ok:
        raise OSError(f"{path}: OpenCV cannot encode this image as PNG")
    data = buf.tobytes()
    ppm = round(dpi / MM_PER_INCH * 1000.0)
    body = b"pHYs" + struct.pack(">IIB", ppm, ppm, 1)
    chunk = struct.pack(">I", 9) + body + struct.pack(">I", zlib.crc32(body))
    end_of_ihdr = 8 + 8 + 13 + 4
    path = Path(path)
    path.write_bytes(data[:end_of_ihdr] + chunk + data[end_of_ihdr:])
    return path


def write_pdf(path: str | Path, image: np.ndarray, dpi: float) -> Path:
    """Write a one-page PDF showing the gray ``image`` at its physical size (``dpi``)."""
    h, w = image.shape
    pw, ph = w / dpi * 72.0, h / dpi * 72.0
    pixels = zlib.compress(np.ascontiguousarray(image, np.uint8).tobytes())
    content = f"q {pw:.3f} 0 0 {ph:.3f} 0 0 cm /Im0 Do Q".encode()
    objects = [
        b"<< /Type /Catalog /Pages 2 0 R >>",
        b"<< /Type /Pages /Kids [3 0 R] /Count 1 >>",
        f"<< /Type /Page /Parent 2 0 R /MediaBox [0 0 {pw:.3f} {ph:.3f}] "
        "/Resources << /XObject << /Im0 5 0 R >> >> /Contents 4 0 R >>".encode(),
        b"<< /Length %d >>\nstream\n" % len(content) + content + b"\nendstream",
        (f"<< /Type /XObject /Subtype /Image /Width {w} /Height {h} /ColorSpace "
         f"/DeviceGray /BitsPerComponent 8 /Filter /FlateDecode /Length {len(pixels)} >>"
         "\nstream\n").encode() + pixels + b"\nendstream",
    ]
    out = bytearray(b"%PDF-1.4\n")
    offsets = []
    for i, obj in enumerate(objects, 1):
        offsets.append(len(out))
        out += b"%d 0 obj\n" % i + obj + b"\nendobj\n"
    xref = len(out)
    out += b"xref\n0 %d\n0000000000 65535 f \n" % (len(objects) + 1)
    out += b"".join(b"%010d 00000 n \n" % o for o in offsets)
    out += b"trailer\n<< /Size %d /Root 1 0 R >>\nstartxref\n%d\n%%%%EOF\n" % (
        len(objects) + 1, xref)
    path = Path(path)
    path.write_bytes(bytes(out))
    return path
