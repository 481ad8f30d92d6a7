"""Tests for kpi.io: image reading, crop boxes, load-cell CSV reading and writing."""
from __future__ import annotations

import re

import cv2
import numpy as np
import pytest

import kpi.io
from kpi.errors import KPIInputError
from kpi.io import CropBox, crop, read_image, read_loadcell_csv, write_image, write_loadcell_csv
from kpi.loadcell import LoadCellSignal


def _escaped(path) -> str:
    return re.escape(str(path))


# ---- images -------------------------------------------------------------------------------

def test_png_round_trip_is_lossless(tmp_path):
    image = np.random.default_rng(0).integers(0, 256, (40, 60, 3), dtype=np.uint8)
    path = tmp_path / "render.png"
    write_image(path, image)
    np.testing.assert_array_equal(read_image(path), image)


def test_jpeg_and_greyscale_read_as_three_channel_bgr(tmp_path):
    grey = np.full((30, 50), 120, np.uint8)
    cv2.imwrite(str(tmp_path / "grey.png"), grey)
    assert read_image(tmp_path / "grey.png").shape == (30, 50, 3)
    colour = np.full((30, 50, 3), (200, 110, 30), np.uint8)
    write_image(tmp_path / "photo.jpg", colour)
    decoded = read_image(tmp_path / "photo.jpg")
    assert decoded.shape == (30, 50, 3) and np.abs(decoded.astype(int) - colour).max() < 8


def test_missing_image_names_file(tmp_path):
    path = tmp_path / "nope.png"
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: file does not exist$"):
        read_image(path)


def test_directory_is_not_an_image(tmp_path):
    with pytest.raises(KPIInputError, match=rf"^{_escaped(tmp_path)}: is not a regular file"):
        read_image(tmp_path)


def test_empty_image_file_names_file(tmp_path):
    path = tmp_path / "empty.png"
    path.write_bytes(b"")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: file is empty \(0 bytes\)"):
        read_image(path)


def test_undecodable_image_names_file(tmp_path):
    path = tmp_path / "broken.jpg"
    path.write_bytes(b"this is not a JPEG at all")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: cannot be decoded as an image \(25 bytes\)"):
        read_image(path)


def test_zero_size_decoded_image_names_file(tmp_path, monkeypatch):
    # no encoder writes a 0 x N image, so the decoder's answer is replaced
    path = tmp_path / "flat.png"
    write_image(path, np.zeros((2, 2, 3), np.uint8))
    monkeypatch.setattr(kpi.io.cv2, "imdecode", lambda data, flags: np.zeros((0, 5, 3), np.uint8))
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: image has zero size \(5 x 0 pixels\)"):
        read_image(path)


def test_write_image_rejects_non_uint8(tmp_path):
    with pytest.raises(KPIInputError, match=r"out\.png: cannot write image of dtype float64"):
        write_image(tmp_path / "out.png", np.zeros((4, 4, 3)))


# ---- crop boxes ----------------------------------------------------------------------------

def test_crop_returns_the_half_open_region():
    image = np.arange(6 * 8 * 3, dtype=np.uint8).reshape(6, 8, 3)
    box = CropBox(2, 1, 5, 4)
    np.testing.assert_array_equal(crop(image, box), image[1:4, 2:5])
    assert (box.width, box.height) == (3, 3)
    assert CropBox.whole(image) == CropBox(0, 0, 8, 6)
    assert CropBox(1.0, 2.0, 3.0, 4.0) == CropBox(1, 2, 3, 4)


def test_crop_box_outside_the_image_names_file_and_size():
    image = np.zeros((6, 8, 3), np.uint8)
    with pytest.raises(
        KPIInputError,
        match=r"^lab\.jpg: crop box \(x0=0, y0=0, x1=9, y1=6\) does not fit the 8 x 6 \(width x height\) image; "
        r"expected x1 <= 8 and y1 <= 6",
    ):
        crop(image, CropBox(0, 0, 9, 6), source="lab.jpg")


@pytest.mark.parametrize(
    "corners,message",
    [
        ((5, 0, 5, 4), r"crop box: \(x0=5, y0=0, x1=5, y1=4\) is not allowed; expected 0 <= x0 < x1 and 0 <= y0 < y1"),
        ((-1, 0, 5, 4), r"crop box: \(x0=-1, y0=0, x1=5, y1=4\) is not allowed"),
        ((0, 4, 5, 2), r"crop box: \(x0=0, y0=4, x1=5, y1=2\) is not allowed"),
        ((0.5, 0, 5, 4), r"crop box: x0 = 0\.5 is not allowed; expected a whole number of pixels"),
        ((True, 0, 5, 4), r"crop box: x0 = True is not allowed"),
    ],
)
def test_invalid_crop_boxes(corners, message):
    with pytest.raises(KPIInputError, match=message):
        CropBox(*corners)


# ---- load-cell CSV -------------------------------------------------------------------------

def _write(path, text: str):
    path.write_text(text, encoding="utf-8")
    return path


def test_loadcell_csv_round_trip(tmp_path):
    time_s = np.round(np.arange(0.0, 3.0, 0.02), 10)
    mass_kg = 40.0 - 10.29 * time_s + np.random.default_rng(1).normal(0.0, 0.3, time_s.size)
    path = tmp_path / "loadcell.csv"
    write_loadcell_csv(path, LoadCellSignal(time_s, mass_kg))
    assert path.read_text().splitlines()[0] == "time_s,mass_kg"
    signal = read_loadcell_csv(path, required_until_s=2.0)
    assert signal.source == str(path)
    np.testing.assert_allclose(signal.time_s, time_s, rtol=1e-9)
    np.testing.assert_allclose(signal.mass_kg, mass_kg, rtol=1e-9)


def test_custom_column_names_bom_extra_columns_and_blank_lines(tmp_path):
    path = tmp_path / "logger.csv"
    path.write_bytes("\ufeffstamp, channel , weight\n0.00,7,40.0\n0.02,7,39.8\n\n0.04,7,39.6\n\n".encode("utf-8"))
    signal = read_loadcell_csv(path, time_column="stamp", mass_column="weight")
    np.testing.assert_allclose(signal.time_s, [0.0, 0.02, 0.04])
    np.testing.assert_allclose(signal.mass_kg, [40.0, 39.8, 39.6])
    path2 = tmp_path / "roundtrip.csv"
    write_loadcell_csv(path2, signal, time_column="stamp", mass_column="weight")
    assert read_loadcell_csv(path2, time_column="stamp", mass_column="weight").mass_kg.tolist() == [40.0, 39.8, 39.6]


def test_missing_csv_names_file(tmp_path):
    path = tmp_path / "loadcell.csv"
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: file does not exist$"):
        read_loadcell_csv(path)


def test_empty_csv_names_file(tmp_path):
    path = _write(tmp_path / "loadcell.csv", "")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: file is empty; expected a header row"):
        read_loadcell_csv(path)


def test_missing_column_lists_the_header(tmp_path):
    path = _write(tmp_path / "loadcell.csv", "time,mass_kg\n0,40\n0.02,39.8\n")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: missing column 'time_s'; the header has \['time', 'mass_kg'\]"):
        read_loadcell_csv(path)


def test_nan_value_names_row_and_column(tmp_path):
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n0,40\n0.02,nan\n")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: column 'mass_kg' is NaN at row 2$"):
        read_loadcell_csv(path)


def test_empty_and_non_numeric_values(tmp_path):
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n0,40\n0.02,\n")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: column 'mass_kg' is empty at row 2$"):
        read_loadcell_csv(path)
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n0,40\n0.02,39.8\n0.04,4O.1\n")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: column 'mass_kg' is not a number at row 3 \('4O\.1'\)"):
        read_loadcell_csv(path)
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n0,40\n0.02,inf\n")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: column 'mass_kg' is not finite at row 2"):
        read_loadcell_csv(path)


def test_non_increasing_time_names_row_and_times(tmp_path):
    rows = [f"{0.02 * k:.2f},{40 - 0.2 * k:.2f}" for k in range(16)] + ["0.36,36.8", "0.34,36.6"]
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n" + "\n".join(rows) + "\n")
    with pytest.raises(
        KPIInputError,
        match=rf"^{_escaped(path)}: column 'time_s' is not increasing at row 18 \(t=0\.34 s after t=0\.36 s\)$",
    ):
        read_loadcell_csv(path)


def test_too_short_record(tmp_path):
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n0,40\n")
    with pytest.raises(KPIInputError, match=rf"^{_escaped(path)}: record has 1 data row; at least 2 needed"):
        read_loadcell_csv(path)
    path = _write(tmp_path / "loadcell.csv", "time_s,mass_kg\n0,40\n0.02,39.8\n1.5,25\n")
    with pytest.raises(
        KPIInputError,
        match=rf"^{_escaped(path)}: record is too short: it ends at t=1\.5 s but must reach t=2 s",
    ):
        read_loadcell_csv(path, required_until_s=2.0)
