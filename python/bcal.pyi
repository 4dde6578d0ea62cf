"""bcal: keep the NASA Li-ion electrochemistry model (Daigle & Kulkarni 2013; progpy's
BatteryElectroChemEOD) true to its cell.

simulate() runs the model, Calibrator calibrates it one reading at a time, diagnose() finds what the
model gets wrong on measured data. Names carry units: time_s, voltage_v, current_a (positive while
discharging), temperature_c; q_mobile in C, r_o in ohm.
"""

import os
from typing import Any, Literal, Optional, TypedDict, Union

import numpy as np
import numpy.typing as npt
import pandas as pd

__version__: str
VEOD_V: float
"""End-of-discharge voltage of the model, V (3.0, progpy's VEOD)."""

PathLike = Union[str, "os.PathLike[str]"]
Kind = Literal["ukf", "adaptive_ukf", "ukf_learned", "rl", "fit", "uncalibrated"]
FloatArray = npt.NDArray[np.float64]

class SimState(TypedDict):
    """Model state per row under progpy's names: charges in C, overpotentials in V, tb in K."""

    qpS: FloatArray
    qpB: FloatArray
    qnB: FloatArray
    qnS: FloatArray
    Vo: FloatArray
    Vsn: FloatArray
    Vsp: FloatArray
    tb: FloatArray

class Simulation(TypedDict):
    time_s: FloatArray
    voltage_v: FloatArray
    current_a: FloatArray
    """Current drawn over the step that starts at each row, A (0 on the EOD row)."""
    temperature_c: FloatArray
    state: SimState
    eod_s: float
    """Time of the first row below VEOD, s."""

class Estimate(TypedDict):
    time_s: float
    q_mobile: float
    q_mobile_lo: Optional[float]
    q_mobile_hi: Optional[float]
    r_o: float
    r_o_lo: Optional[float]
    r_o_hi: Optional[float]
    eod_s: Optional[float]
    """Predicted end of discharge, absolute time, s, at eod_current_a (or eod_power_w)."""
    eod_current_a: Optional[float]
    """Mean discharge current of the loaded readings so far, A; where the load switches about as often as it
    is sampled (a square wave read once per half-period), the mean current over time since the load came on;
    under a load held at constant power (eod_power_w), the mean current the model draws at that power from
    now to its own end (it rises as the voltage falls), before any rule moves that end."""
    eod_power_w: Optional[float]
    """The power the prediction assumes, W, where the load has been held at constant power (the loaded
    readings' power varied, sd over mean, less than half as much as their current); None under a current."""
    eod_lo_s: Optional[float]
    eod_hi_s: Optional[float]
    """The prediction's 90 % interval, absolute times, s: learned from how the stream's predictions fared
    on its last 10 discharges followed to the cut-off (not those started far short of full, more than 150 mV
    below the last three's rests: scored, they teach no rule), with what the discharge's start adds (its rest
    voltage known to the sensor's noise, through the open-circuit curve: several % of the charge on the curve's
    plateau, nil near full); None until 9 of them are scored."""
    delivered_ah: Optional[float]
    """The charge this discharge will have delivered at its end, Ah: what its readings drew so far plus
    eod_current_a until eod_s (from a full cell, its capacity at that current as a cycler measures it; under a
    power, the charge the model draws to its own end, and on to eod_s at the current the power draws at the
    cut-off). Once
    the discharge has crossed its cut-off, the charge measured to the crossing. None before the load and in
    a piece of a discharge whose start the stream did not see (after lost readings)."""
    delivered_lo_ah: Optional[float]
    delivered_hi_ah: Optional[float]
    """delivered_ah at eod_lo_s and eod_hi_s (None once the cut-off is crossed)."""
    eod_from_prior: bool
    """Whether eod_s is the prior alone's prediction (the estimate the discharge started from, never moved
    by its readings): where the prior beat what it replaces (the calibrator's own, recentred where that
    serves) on at least 8 of the last 10 discharges followed to the cut-off and in their mean, except after
    a rest of more than a day."""
    eod_recentred: bool
    """Whether eod_s is the calibrator's own prediction moved by its median signed error at this share of
    the discharge over the last 10 discharges followed to the cut-off: where that beat the calibrator's own
    on at least 8 of them and in their mean, except where the prior alone predicts or after a rest of more
    than a day."""
    eod_on_voltage_change: bool
    """Whether eod_s is the calibrator's own prediction moved by the error its last 15 discharges followed to
    the cut-off expect at this share, as a line in the voltage change (this discharge's voltage against the
    one before at the same time since the load came on, the last minute's mean): where that beat what the
    recentring gives on at least 8 of the last 10 and in their mean, except where the prior alone predicts
    or after a rest of more than a day."""
    eod_prior_weight: float
    """The prior alone's weight in eod_s: 1 where it predicts alone (eod_from_prior), its weight in the blend
    of the calibrator's prediction (as delivered) with the prior's where one is learned (by inverse mean
    squared error at this share over the last 15 discharges followed to the cut-off, from the ninth on)
    times that blend's share against the previous discharge's fit (1 - eod_previous_weight), else 0. Where it is below 1, eod_recentred and eod_on_voltage_change tell which of the calibrator's
    predictions is blended."""
    eod_previous_weight: float
    """The previous discharge's fit's weight in eod_s: the blend above is blended in turn with the prediction
    of the fit the last discharge measured, carried over as it is (recentred where that serves), by the same
    rule on the discharges that followed rests of up to a day; 0 after a longer rest (the fit carries no
    recovery), where the prior alone predicts, or before 8 such discharges have been followed."""
    eod_learned_weight: float
    """Kind "ukf_learned": the weight, in eod_s, of what the rules above deliver moved by the signed error the
    learner on the stream's own record expects of it at this share (from its last errors, the rest before
    this discharge, how warm its loaded readings run against the discharges before it that started at
    its temperature, and how far their mean current so far moved from the last discharge's; least squares
    on the last 30 discharges followed to the cut-off), blended with the
    unmoved by the two's records over the last 15; 0 for other kinds and until 19 discharges have been
    followed to the cut-off."""
    discharge: int
    """The discharge the reading belongs to, from 0: a new one after a charge or a gap of more than
    half an hour, started from what the last one told (the charge its end measured where it reached
    the cut-off, else the estimate it ended with)."""

def simulate(
    load_w: Optional[float] = None,
    current_a: Optional[float] = None,
    q_mobile: float = 7600.0,
    ro: float = 0.117215,
    dt_s: float = 1.0,
    thermal: bool = False,
    max_steps: int = 200_000,
    steps: Optional[list[tuple[float, float]]] = None,
) -> Simulation:
    """One discharge of the model from a new cell's state until the first step below VEOD (3.0 V),
    stepped by explicit Euler: what `bcal simulate` runs.

    Give exactly one of `load_w` (constant power, W; the current is P / V at the start of each step)
    and `current_a` (constant current, A). `q_mobile` (C) and `ro` (ohm) are the degradation
    parameters (new cell: 7600 C, 0.117215 ohm). `thermal` turns on the bulk temperature's heat
    balance (progpy always runs it; off, the cell stays at 292.1 K). `steps`: later load steps as
    (start_s, value) pairs in the first load's unit (8 W, then 16 W from 1000 s:
    `load_w=8.0, steps=[(1000.0, 16.0)]`).

    Raises ValueError with the CLI's message for a bad argument or when VEOD is not reached within
    `max_steps`.

    >>> bcal.simulate(load_w=8.0)["eod_s"]
    3102.0
    """

def diagnose(
    data: PathLike,
    cell: Optional[str] = None,
    cycles: Optional[str] = None,
    holdout: Optional[str] = None,
    stride: int = 1,
    cutoff_v: Optional[float] = None,
    current_sign: Literal["auto", "discharge-positive", "discharge-negative"] = "auto",
    ambient_c: Optional[float] = None,
) -> dict[str, Any]:
    """Diagnose measured discharges as `bcal diagnose` does (without writing files): fit the model per
    cycle, find what it gets wrong, name the cause, extend the model, judged on held-out cycles.

    `data`: a NASA PCoE folder (`cell` required, e.g. "B0005") or a CSV
    (time_s,voltage_v,current_a[,temperature_c][,cycle]). `cycles`, `holdout`: "A..B" (NASA from 1, a CSV as
    its cycle column counts; inclusive; default three quarters of the cycles `bcal calibrate` trains on against the last quarter,
    B0005 1..30 against 31..40, so the diagnosis feeds `bcal calibrate --model`; a life under 24
    discharges: its first third against the rest).

    Returns diagnosis.json's content (cause, ranking, base and extended models, per-cycle fits,
    residual structure) plus `read_notes` and `cutoff_source`. Raises FileNotFoundError / OSError for
    unreadable data, ValueError with the CLI's message for anything else.
    """

class Calibrator:
    """A calibrator fed one reading at a time, no look-ahead: estimates of qMobile (C) and Ro (ohm)
    with 90 % intervals, and the end of discharge predicted from the calibrated state. The same code
    as `bcal calibrate --follow`: the same readings give the same estimates. Readings may span many
    discharges: after a charge or a gap of more than half an hour a new one starts, calibrated anew
    from what the last one told (the charge its end measured, else the estimate it ended with), and
    the end of discharge gets a 90 % interval learned from the discharges followed to their cut-off.

    `kind`: "ukf" (joint unscented Kalman filter), "adaptive_ukf", "ukf_learned" (the joint UKF with
    its end of discharge moved by the learner on the stream's own record, as `bcal calibrate`'s
    ukf_learned), "rl" (an RL policy; `policy` is its .bcalpol file), "fit" (the window fit, no
    learning) or "uncalibrated" (the prior).
    `model`: the doctor's extended model (diagnosis.json, or its folder); its per-cycle values start at the last
    training fits and are refitted on every discharge followed to the cut-off. `config`: a bcal config TOML
    (`bcal cell-config` writes one per cell); its lifetime model (else the diagnosis's) moves what one discharge
    hands the next by the fade and the capacity a rest gives back. `ambient_c`: temperature of readings that
    give none before any other did within half an hour. `cutoff_v`: the cut-off of the EOD predictions, V
    (default the config's, else 3.0).

    Raises ValueError for a bad kind or file content, FileNotFoundError / OSError for unreadable
    files.
    """

    def __init__(
        self,
        kind: Kind,
        policy: Optional[PathLike] = None,
        model: Optional[PathLike] = None,
        config: Optional[PathLike] = None,
        ambient_c: Optional[float] = None,
        cutoff_v: Optional[float] = None,
    ) -> None: ...
    @property
    def kind(self) -> str:
        """The calibrator's kind."""
    @property
    def readings(self) -> int:
        """Readings taken so far (refused ones not counted)."""
    @property
    def spec(self) -> dict[str, Any]:
        """The calibrator's setting (ranges, prior, cut-off, model) as bcal's config writes it."""
    @property
    def widened_ranges(self) -> list[list[float]] | None:
        """The ranges the stream widened the setting's to after two discharges in a row handed on a fit at the
        same edge of one, `[[q_mobile_lo_c, q_mobile_hi_c], [r_o_lo_ohm, r_o_hi_ohm]]`; None while it has not."""
    @property
    def range_edges(self) -> dict[str, int]:
        """Discharges finished so far (`discharges`: each counts once it has handed its fit on, when the next
        begins) and those whose fit sat at an edge of the setting's ranges (`at_edge`; per edge
        `q_mobile_floor`, `q_mobile_top`, `r_o_floor`, `r_o_top`): a cell outside the ranges is followed at
        their edge and its predictions are far off; give it its own setting (`config=`, from `bcal
        cell-config`)."""
    def step(
        self,
        time_s: float,
        voltage_v: float,
        current_a: float,
        temperature_c: Optional[float] = None,
    ) -> Estimate:
        """Takes the next reading (time order; current positive while discharging) and returns the
        estimate. A temperature of None or NaN (pandas' missing value) reads as the last reading's (within
        half an hour; else the ambient). A reading that is not finite, not a cell's voltage, not later than
        the last or a current glitch (a step of 5 A or more that the voltage does not follow; a level refused
        twice in a row is taken at the third) raises ValueError and leaves the calibrator as it was."""
    def predict_eod_s(self, current_a: Optional[float] = None, *, power_w: Optional[float] = None) -> Optional[float]:
        """End of discharge (absolute time, s) if the cell now draws `current_a` (A), or `power_w` (W: the
        current P / V rising as the voltage falls), to the cut-off; exactly one of them. None before the first
        reading or beyond the 40 000 s horizon."""
    def state(self) -> Optional[dict[str, float]]:
        """The calibrated model state under progpy's names (qpS, qpB, qnB, qnS in C; Vo, Vsn, Vsp in V;
        tb in K), or None before the first reading."""
    def run(self, df: pd.DataFrame) -> pd.DataFrame:
        """Feeds every row of `df` (columns time_s, voltage_v, current_a, optionally temperature_c; or
        the same quantities in other units, named as the CSV readers read them: time_ms, current_ma,
        Voltage / mV, NASA's Voltage_measured ...) and returns one row per reading: the keys of `step` (NaN
        for None) and `row`, the reading's position. A missing temperature (NaN) reads as the last reading's
        (within half an hour; else the ambient), as an empty CSV field of `bcal calibrate --follow` does. A bad row raises ValueError naming its position."""
