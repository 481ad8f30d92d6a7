"""Files in and out of the KPI measurements: photos/renders, crop boxes, load-cell CSVs.

Contract:

* :func:`read_image` returns an 8-bit BGR array ``[H, W, 3]`` (OpenCV order) from a PNG or
  JPEG file, or raises :class:`kpi.errors.KPIInputError` naming the file for a missing path, a
  directory, an empty (0-byte) file, bytes that do not decode as an image, or an image with
  zero width or height.
* :class:`CropBox` is a region of interest in pixels, half-open: columns ``x0 <= x < x1``,
  rows ``y0 <= y < y1``, origin at the image's top-left corner. :func:`crop` checks it
  against the image size and names the image when it does not fit.
* :func:`read_loadcell_csv` reads a comma-separated file with a header row and (by default)
  the columns ``time_s`` (s) and ``mass_kg`` (upper-box mass, kg); other columns are ignored.
  Missing file, missing columns, empty, non-numeric or non-finite values, a time column that
  does not increase, and a record too short for the fit window each raise KPIInputError naming
  the file, the column and the data row (1-based, header not counted). :func:`write_loadcell_csv`
  writes the same format.
"""
from __future__ import annotations

import csv
import math
import os
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from kpi.errors import bad_input
from kpi.loadcell import LoadCellSignal

TIME_COLUMN = "time_s"
MASS_COLUMN = "mass_kg"


def _existing_file(path: str | os.PathLike) -> Path:
    path = Path(path)
    if not path.exists():
        raise bad_input(str(path), "file does not exist")
    if not path.is_file():
        raise bad_input(str(path), "is not a regular file (a directory?)")
    return path


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Read a PNG/JPEG photo or render as 8-bit BGR ``[H, W, 3]``.

    Grey-scale files are expanded to three channels; 16-bit files are scaled to 8 bits.
    """
    path = _existing_file(path)
    data = np.fromfile(path, dtype=np.uint8)
    if data.size == 0:
        raise bad_input(str(path), "file is empty (0 bytes); expected a PNG or JPEG image")
    image = cv2.imdecode(data, cv2.IMREAD_COLOR)
    if image is None:
        raise bad_input(
            str(path), f"cannot be decoded as an image ({data.size} bytes); expected a PNG or JPEG file"
        )
    if image.size == 0 or image.shape[0] == 0 or image.shape[1] == 0:
        raise bad_input(str(path), f"image has zero size ({image.shape[1]} x {image.shape[0]} pixels)")
    return image


def write_image(path: str | os.PathLike, image_bgr: np.ndarray) -> None:
    """Write an 8-bit BGR image; the format follows the file suffix (.png, .jpg)."""
    path = Path(path)
    image = np.asarray(image_bgr)
    if image.dtype != np.uint8 or image.ndim not in (2, 3) or image.size == 0:
        raise bad_input(
            str(path), f"cannot write image of dtype {image.dtype} and shape {image.shape}; "
            "expected non-empty uint8 [H, W] or [H, W, 3]"
        )
    ok, encoded = cv2.imencode(path.suffix or ".png", image)
    if not ok:
        raise bad_input(str(path), f"OpenCV cannot encode an image with suffix {path.suffix!r}")
    encoded.tofile(path)


@dataclass(frozen=True)
class CropBox:
    """Region of interest in pixels: columns ``x0 <= x < x1``, rows ``y0 <= y < y1``."""

    x0: int
    y0: int
    x1: int
    y1: int

    def __post_init__(self) -> None:
        for name in ("x0", "y0", "x1", "y1"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                if isinstance(value, (float, np.floating)) and float(value).is_integer():
                    object.__setattr__(self, name, int(value))
                    continue
                raise bad_input(
                    "crop box", f"{name} = {value!r} is not allowed; expected a whole number of pixels"
                )
            object.__setattr__(self, name, int(value))
        if not (0 <= self.x0 < self.x1 and 0 <= self.y0 < self.y1):
            raise bad_input(
                "crop box",
                f"(x0={self.x0}, y0={self.y0}, x1={self.x1}, y1={self.y1}) is not allowed; "
                "expected 0 <= x0 < x1 and 0 <= y0 < y1 (pixels)",
            )

    @property
    def width(self) -> int:
        return self.x1 - self.x0

    @property
    def height(self) -> int:
        return self.y1 - self.y0

    @classmethod
    def whole(cls, image: np.ndarray) -> "CropBox":
        """The box covering the whole image."""
        return cls(0, 0, int(image.shape[1]), int(image.shape[0]))


def crop(image: np.ndarray, box: CropBox, source: str = "image") -> np.ndarray:
    """The part of ``image`` inside ``box`` (a view, not a copy)."""
    height, width = image.shape[:2]
    if box.x1 > width or box.y1 > height:
        raise bad_input(
            source,
            f"crop box (x0={box.x0}, y0={box.y0}, x1={box.x1}, y1={box.y1}) does not fit the "
            f"{width} x {height} (width x height) image; expected x1 <= {width} and y1 <= {height}",
        )
    return image[box.y0 : box.y1, box.x0 : box.x1]


def read_loadcell_csv(
    path: str | os.PathLike,
    *,
    time_column: str = TIME_COLUMN,
    mass_column: str = MASS_COLUMN,
    required_until_s: float | None = None,
) -> LoadCellSignal:
    """Read a load-cell record (time in s, upper-box mass in kg).

    Args:
        path: CSV file with a header row.
        time_column, mass_column: header names of the two columns to read.
        required_until_s: if given, the record must reach at least this time (e.g. the end of
            the mass-flow fit window), else KPIInputError.
    """
    path = _existing_file(path)
    name = str(path)
    with open(path, newline="", encoding="utf-8-sig") as handle:
        reader = csv.reader(handle)
        header = next(reader, None)
        if header is None:
            raise bad_input(name, "file is empty; expected a header row with "
                            f"'{time_column}' and '{mass_column}'")
        header = [column.strip() for column in header]
        missing = [column for column in (time_column, mass_column) if column not in header]
        if missing:
            raise bad_input(
                name,
                f"missing column{'s' if len(missing) > 1 else ''} "
                f"{', '.join(repr(m) for m in missing)}; the header has {header}",
            )
        indices = {column: header.index(column) for column in (time_column, mass_column)}
        times: list[float] = []
        masses: list[float] = []
        for row in reader:
            if not row or all(not cell.strip() for cell in row):
                continue
            row_number = len(times) + 1
            values = {}
            for column, index in indices.items():
                text = row[index].strip() if index < len(row) else ""
                if not text:
                    raise bad_input(name, f"column '{column}' is empty at row {row_number}")
                try:
                    value = float(text)
                except ValueError:
                    raise bad_input(
                        name, f"column '{column}' is not a number at row {row_number} ({text!r})"
                    ) from None
                if math.isnan(value):
                    raise bad_input(name, f"column '{column}' is NaN at row {row_number}")
                if not math.isfinite(value):
                    raise bad_input(name, f"column '{column}' is not finite at row {row_number} ({text!r})")
                values[column] = value
            if times and values[time_column] <= times[-1]:
                raise bad_input(
                    name,
                    f"column '{time_column}' is not increasing at row {row_number} "
                    f"(t={values[time_column]:g} s after t={times[-1]:g} s)",
                )
            times.append(values[time_column])
            masses.append(values[mass_column])
    if len(times) < 2:
        raise bad_input(
            name, f"record has {len(times)} data row{'' if len(times) == 1 else 's'}; at least 2 needed"
        )
    if required_until_s is not None and times[-1] < required_until_s:
        raise bad_input(
            name,
            f"record is too short: it ends at t={times[-1]:g} s but must reach "
            f"t={required_until_s:g} s (end of the mass-flow fit window)",
        )
    return LoadCellSignal(time_s=np.array(times), mass_kg=np.array(masses), source=name)


def write_loadcell_csv(
    path: str | os.PathLike,
    signal: LoadCellSignal,
    *,
    time_column: str = TIME_COLUMN,
    mass_column: str = MASS_COLUMN,
) -> None:
    """Write a load-cell record in the format :func:`read_loadcell_csv` reads."""
    with open(path, "w", newline="", encoding="utf-8") as handle:
        writer = csv.writer(handle)
        writer.writerow([time_column, mass_column])
        for time_s, mass_kg in zip(signal.time_s, signal.mass_kg):
            writer.writerow([format(time_s, ".10g"), format(mass_kg, ".10g")])
