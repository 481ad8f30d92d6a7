"""kpi: draw-down test KPIs measured from images and load-cell records, as the lab does.

Contract: ``kpi`` knows nothing of the simulator. It reads front-view photos or renders and
load-cell CSVs (:mod:`kpi.io`) and measures the paper's KPIs (section 2.3):

* :mod:`kpi.angles` -- angle of repose (lower-box heap) and shear angle (upper-box funnel), deg;
* :mod:`kpi.segregation` -- vertical and horizontal segregation RSD of pellets and sinter;
* :mod:`kpi.loadcell` -- mass flow rate (kg/s), mass in the lower box (kg), discharge end (s);
* :mod:`kpi.colors` -- the render colour convention the segmentation defaults expect;
* :mod:`kpi.cli` -- the ``torchdem-kpi`` command.

SI units inside, degrees only for the reported angles. Every bad input raises
:class:`kpi.errors.KPIInputError` naming the file (or config field) and the problem.
"""
from kpi.angles import SurfaceAngle, SurfaceConfig, angle_of_repose, shear_angle
from kpi.errors import KPIInputError
from kpi.io import CropBox, read_image, read_loadcell_csv, write_loadcell_csv
from kpi.loadcell import Discharge, DischargeConfig, LoadCellSignal, fit_mass_flow_rate, measure_discharge
from kpi.segregation import Segregation, SegmentationConfig, measure_segregation

__all__ = [
    "CropBox",
    "Discharge",
    "DischargeConfig",
    "KPIInputError",
    "LoadCellSignal",
    "Segregation",
    "SegmentationConfig",
    "SurfaceAngle",
    "SurfaceConfig",
    "angle_of_repose",
    "fit_mass_flow_rate",
    "measure_discharge",
    "measure_segregation",
    "read_image",
    "read_loadcell_csv",
    "shear_angle",
    "write_loadcell_csv",
]
