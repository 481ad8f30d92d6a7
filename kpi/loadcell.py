"""Mass flow rate, lower-box mass and discharge end from the upper-box load-cell signal.

Contract (paper section 2.3.3): the load cells weigh the upper box at 50 Hz while it
discharges. The raw signal is smoothed with a Gaussian filter whose width is given in
seconds (so it means the same at any sampling rate); the steady **mass flow rate** is minus
the slope of the least-squares straight line through the smoothed mass over a window after
the gate opens (0.5 s to 2.0 s by default, the paper's window); the **mass in the lower box**
is the initial mass minus the final, steady upper-box mass (mean of the smoothed mass over the
last ``final_window_s`` of the record); the **discharge end** is the first time after the fit
window starts at which the smoothed mass comes within ``end_tolerance_kg`` of that final mass.
:func:`measure_discharge` measures all three and refuses a record that ends before the
discharge has; :func:`fit_mass_flow_rate` gives the flow rate alone, which needs only the fit
window (a simulation stopped while the last grains trickle out still has a flow rate).

Units: time in s, mass in kg, mass flow rate in kg/s (positive while the box empties).
Time is the record's own axis; ``gate_open_s`` says where on it the gate opened (0 s by
default, as in the paper's Fig. 6). The filter assumes uniform sampling; a record with gaps
or jitter beyond half a sampling interval is rejected rather than silently mis-filtered.

Every bad input raises :class:`kpi.errors.KPIInputError` naming the record's source.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping

import numpy as np
from scipy.ndimage import gaussian_filter1d

from kpi.errors import bad_input, out_of_range

#: Largest allowed deviation of one sampling interval from the median interval, as a fraction
#: of the median: more than this is a dropped sample or a clock jump, not logger jitter.
SAMPLING_JITTER_FRACTION = 0.5


def _read_only(array: np.ndarray) -> np.ndarray:
    array.setflags(write=False)
    return array


@dataclass(frozen=True)
class LoadCellSignal:
    """Upper-box mass against time.

    Attributes:
        time_s: ``[T]`` sample times in s, finite and strictly increasing.
        mass_kg: ``[T]`` upper-box mass in kg, finite.
        source: where the record came from (file path), used in error messages.
    """

    time_s: np.ndarray
    mass_kg: np.ndarray
    source: str = "load-cell signal"

    def __post_init__(self) -> None:
        time_s = np.array(self.time_s, dtype=np.float64)
        mass_kg = np.array(self.mass_kg, dtype=np.float64)
        if time_s.ndim != 1 or mass_kg.ndim != 1 or time_s.shape != mass_kg.shape:
            raise bad_input(
                self.source,
                f"time_s and mass_kg must be 1-D arrays of equal length; got shapes "
                f"{time_s.shape} and {mass_kg.shape}",
            )
        if time_s.size < 2:
            raise bad_input(self.source, f"record has {time_s.size} samples; at least 2 needed")
        for name, values in (("time_s", time_s), ("mass_kg", mass_kg)):
            bad = np.flatnonzero(~np.isfinite(values))
            if bad.size:
                raise bad_input(
                    self.source, f"{name} is not finite at sample {bad[0]} ({values[bad[0]]!r})"
                )
        steps = np.diff(time_s)
        back = np.flatnonzero(steps <= 0)
        if back.size:
            k = back[0] + 1
            raise bad_input(
                self.source,
                f"time_s is not increasing at sample {k} "
                f"(t={time_s[k]:g} s after t={time_s[k - 1]:g} s)",
            )
        object.__setattr__(self, "time_s", _read_only(time_s))
        object.__setattr__(self, "mass_kg", _read_only(mass_kg))

    @property
    def sampling_interval_s(self) -> float:
        """Median interval between samples in s (0.02 s for the paper's 50 Hz logger)."""
        return float(np.median(np.diff(self.time_s)))


@dataclass(frozen=True)
class DischargeConfig:
    """How the load-cell signal is reduced to KPIs.

    Attributes:
        filter_sigma_s: standard deviation of the Gaussian smoothing kernel in s
            (0 disables smoothing). The paper does not state its width; 0.1 s (5 samples at
            50 Hz) removes load-cell noise without blurring the 1.5 s fit window.
        gate_open_s: time on the record's axis at which the gate opened, in s.
        fit_window_s: (start, end) of the steady-flow fit window in s after the gate opened.
        final_window_s: length in s of the record's tail averaged for the final mass.
        end_tolerance_kg: the discharge has ended once the smoothed mass is within this
            many kg of the final mass.
    """

    filter_sigma_s: float = 0.1
    gate_open_s: float = 0.0
    fit_window_s: tuple[float, float] = (0.5, 2.0)
    final_window_s: float = 0.5
    end_tolerance_kg: float = 0.2

    def __post_init__(self) -> None:
        source = "DischargeConfig"
        if not (np.isfinite(self.filter_sigma_s) and self.filter_sigma_s >= 0):
            raise out_of_range(source, "filter_sigma_s", self.filter_sigma_s, "a finite value >= 0 s")
        if not np.isfinite(self.gate_open_s):
            raise out_of_range(source, "gate_open_s", self.gate_open_s, "a finite time in s")
        if len(self.fit_window_s) != 2:
            raise out_of_range(source, "fit_window_s", self.fit_window_s, "(start, end) in s")
        start, end = (float(v) for v in self.fit_window_s)
        if not (np.isfinite(start) and np.isfinite(end) and 0 <= start < end):
            raise out_of_range(
                source, "fit_window_s", self.fit_window_s, "finite (start, end) with 0 <= start < end s"
            )
        object.__setattr__(self, "fit_window_s", (start, end))
        if not (np.isfinite(self.final_window_s) and self.final_window_s > 0):
            raise out_of_range(source, "final_window_s", self.final_window_s, "a finite value > 0 s")
        if not (np.isfinite(self.end_tolerance_kg) and self.end_tolerance_kg > 0):
            raise out_of_range(source, "end_tolerance_kg", self.end_tolerance_kg, "a finite value > 0 kg")

    @property
    def fit_window_end_s(self) -> float:
        """Time on the record's axis the record must at least reach, in s."""
        return self.gate_open_s + self.fit_window_s[1]


@dataclass(frozen=True)
class Discharge:
    """Draw-down KPIs from one load-cell record.

    Attributes:
        mass_flow_rate_kg_s: steady mass flow rate, minus the fitted slope, kg/s.
        lower_box_mass_kg: initial mass minus final upper-box mass, kg.
        initial_mass_kg: total mass filled into the upper box, kg.
        final_upper_mass_kg: steady upper-box mass at the end of the record, kg.
        discharge_end_s: time on the record's axis at which the discharge ended, s.
        discharge_duration_s: discharge end minus gate opening, s.
        fit_window_s: (start, end) of the fit on the record's time axis, s.
        fit_intercept_kg: the fitted line is ``mass = fit_intercept_kg - mass_flow_rate_kg_s * t``.
        smoothed_mass_kg: ``[T]`` the Gaussian-filtered mass, kg, for plotting.
    """

    mass_flow_rate_kg_s: float
    lower_box_mass_kg: float
    initial_mass_kg: float
    final_upper_mass_kg: float
    discharge_end_s: float
    discharge_duration_s: float
    fit_window_s: tuple[float, float]
    fit_intercept_kg: float
    smoothed_mass_kg: np.ndarray


def smooth_mass(signal: LoadCellSignal, filter_sigma_s: float) -> np.ndarray:
    """Gaussian-filtered mass ``[T]`` in kg; the kernel width is given in s.

    Raises KPIInputError if the sampling is not uniform (see ``SAMPLING_JITTER_FRACTION``).
    """
    steps = np.diff(signal.time_s)
    median_step = float(np.median(steps))
    off = np.flatnonzero(np.abs(steps - median_step) > SAMPLING_JITTER_FRACTION * median_step)
    if off.size:
        k = off[0] + 1
        raise bad_input(
            signal.source,
            f"sampling interval before t={signal.time_s[k]:g} s is {steps[k - 1]:g} s but the "
            f"median interval is {median_step:g} s; the Gaussian filter needs uniform sampling "
            f"(each interval within {SAMPLING_JITTER_FRACTION:.0%} of the median)",
        )
    if filter_sigma_s == 0:
        return signal.mass_kg.copy()
    return gaussian_filter1d(signal.mass_kg, sigma=filter_sigma_s / median_step, mode="nearest")


def fit_mass_flow_rate(signal: LoadCellSignal, config: DischargeConfig = DischargeConfig()
                       ) -> tuple[float, float, np.ndarray]:
    """Mass flow rate of a draw-down record: minus the slope of the straight line fitted to the
    Gaussian-filtered upper-box mass over the fit window (section 2.3.2), whether or not the
    record goes on until the discharge has ended.

    Returns:
        (mass flow rate kg/s, intercept of the fitted line kg, smoothed mass ``[T]`` kg).
    Raises:
        KPIInputError: the record does not cover the fit window or has too few samples in it.
    """
    source = signal.source
    time_s = signal.time_s
    window_start = config.gate_open_s + config.fit_window_s[0]
    window_end = config.gate_open_s + config.fit_window_s[1]
    if time_s[0] > window_start or time_s[-1] < window_end:
        raise bad_input(
            source,
            f"record covers t={time_s[0]:g}..{time_s[-1]:g} s but the mass-flow fit window is "
            f"t={window_start:g}..{window_end:g} s (gate opens at {config.gate_open_s:g} s, "
            f"window {config.fit_window_s[0]:g}-{config.fit_window_s[1]:g} s after)",
        )
    smoothed = smooth_mass(signal, config.filter_sigma_s)
    in_window = (time_s >= window_start) & (time_s <= window_end)
    if np.count_nonzero(in_window) < 3:
        raise bad_input(
            source,
            f"only {np.count_nonzero(in_window)} samples in the fit window "
            f"t={window_start:g}..{window_end:g} s; at least 3 needed",
        )
    slope, intercept = np.polyfit(time_s[in_window], smoothed[in_window], deg=1)
    return -float(slope), float(intercept), smoothed


def measure_discharge(
    signal: LoadCellSignal, initial_mass_kg: float, config: DischargeConfig = DischargeConfig()
) -> Discharge:
    """Mass flow rate, lower-box mass and discharge end of one draw-down record.

    Args:
        signal: upper-box mass against time.
        initial_mass_kg: mass filled into the upper box, kg (40 kg in the paper).
        config: filter width and windows.

    Raises:
        KPIInputError: the record does not cover the fit window, has too few samples in it,
            is still discharging at its end, or the initial mass is below the final mass.
    """
    source = signal.source
    if not (np.isfinite(initial_mass_kg) and initial_mass_kg > 0):
        raise out_of_range(source, "initial_mass_kg", initial_mass_kg, "a finite mass > 0 kg")
    time_s = signal.time_s
    window_start = config.gate_open_s + config.fit_window_s[0]
    window_end = config.gate_open_s + config.fit_window_s[1]
    mass_flow_rate, intercept, smoothed = fit_mass_flow_rate(signal, config)

    tail_start = time_s[-1] - config.final_window_s
    if tail_start < window_end:
        raise bad_input(
            source,
            f"record ends at t={time_s[-1]:g} s, so its last {config.final_window_s:g} s overlap "
            f"the fit window ending at t={window_end:g} s; the record must continue until the "
            f"upper-box mass is steady",
        )
    final_mass = float(np.mean(smoothed[time_s >= tail_start]))

    after_start = time_s >= window_start
    ended = after_start & (smoothed <= final_mass + config.end_tolerance_kg)
    end_index = int(np.argmax(ended))
    discharge_end = float(time_s[end_index])
    if not ended[end_index] or discharge_end > tail_start:
        raise bad_input(
            source,
            f"upper-box mass is still falling in the last {config.final_window_s:g} s of the "
            f"record (it reaches within {config.end_tolerance_kg:g} kg of its final value "
            f"{final_mass:.3f} kg only at t={discharge_end:g} s, after t={tail_start:g} s); "
            f"record until the discharge has ended",
        )
    lower_box_mass = float(initial_mass_kg) - final_mass
    # a box that let nothing out reads its fill again, within the load cell's resolution: the
    # end tolerance bounds that reading's spread, so a final mass that far above the fill is an error
    if lower_box_mass < -config.end_tolerance_kg:
        raise bad_input(
            source,
            f"initial_mass_kg = {initial_mass_kg:g} kg is below the final upper-box mass "
            f"{final_mass:.3f} kg by more than the end tolerance {config.end_tolerance_kg:g} kg; expected "
            f"the total mass filled into the upper box",
        )
    lower_box_mass = max(lower_box_mass, 0.0)
    return Discharge(
        mass_flow_rate_kg_s=mass_flow_rate,
        lower_box_mass_kg=lower_box_mass,
        initial_mass_kg=float(initial_mass_kg),
        final_upper_mass_kg=final_mass,
        discharge_end_s=discharge_end,
        discharge_duration_s=discharge_end - config.gate_open_s,
        fit_window_s=(window_start, window_end),
        fit_intercept_kg=float(intercept),
        smoothed_mass_kg=_read_only(smoothed),
    )


def discharge_state(kpis: Mapping[str, float]) -> str:
    """``"ended"``, ``"not ended"`` (stopped while the upper box still emptied) or ``"not recorded"``
    (a run made before runs reported ``discharge_ended``), from a draw down run's KPIs (``torchdem.drawdown``: ``discharge_ended`` is 1 when
    :func:`measure_discharge` found the discharge ended within the record, else 0)."""
    ended = kpis.get("discharge_ended")
    return "not recorded" if ended is None or ended != ended else "ended" if ended == 1 else "not ended"


def discharge_jammed(kpis: Mapping[str, float]) -> bool:
    """Whether a draw down run's discharge jammed (``torchdem.drawdown``: ``discharge_jammed`` is 1
    when less than ``JAM_FRACTION`` of the fill left the upper box); False for runs made before it
    was reported."""
    return kpis.get("discharge_jammed") == 1
