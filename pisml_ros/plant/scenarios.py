"""Scenarios of the paper's protocol (DESIGN.md): training, test and small-signal sets.

Each scenario is a list of :class:`Event` schedules; :func:`generate` turns one
into a :class:`~pisml_ros.data.Dataset` by starting every trajectory at the
plant's equilibrium for its pre-event grid voltage and simulating at 10 kHz.
Event times are rounded to the sample grid (a HIL applies them at a sample).
"""
from __future__ import annotations

import dataclasses
import math

import numpy as np

from .. import __version__
from ..data import Dataset, Trajectory
from ..signals import SAMPLE_RATE_HZ
from ..integrate import simulate
from .parameters import ParameterError

SCENARIOS = ("train", "test", "smallsignal")


@dataclasses.dataclass
class Schedule:
    """Grid voltage/phase of one trajectory: initial values and timed steps.

    ``steps`` holds ``(t, "ug" | "theta_g", value)``: from time t on, the input
    takes ``value`` (absolute, p.u. or rad).
    """

    ug0: float
    theta0: float = 0.0
    steps: list = dataclasses.field(default_factory=list)
    label: str = ""

    def sample(self, n: int, dt: float) -> np.ndarray:
        """Inputs at the n sample times, shape (n, 2)."""
        u = np.empty((n, 2))
        u[:, 0], u[:, 1] = self.ug0, self.theta0
        for t, name, value in sorted(self.steps, key=lambda s: s[0]):
            k = int(round(t / dt))
            u[k:, 0 if name == "ug" else 1] = value
        return u


def training_schedules(n_traj: int = 12, seed: int = 0, duration: float = 0.04,
                       ug_range: tuple = (0.8, 1.2), jump_deg: tuple = (5.0, 10.0)) -> list[Schedule]:
    """Paper training set: start at equilibrium with ug0 ~ U[0.8, 1.2]; a sag that keeps
    80–100 % of the pre-event voltage (random start, random length, may last to the end)
    and a ±5–10° phase jump, at random times.

    ``ug_range`` and ``jump_deg`` (magnitude, degrees) change the pre-event voltages and the phase
    jumps (other scenarios than the paper's, as bench/scenarios_bench.py runs); the same seed gives
    the same event times and sag depths."""
    rng = np.random.default_rng(seed)
    schedules = []
    for k in range(n_traj):
        ug0 = rng.uniform(*ug_range)
        sag_level = ug0 * rng.uniform(0.8, 1.0)
        t_sag = rng.uniform(0.1, 0.6) * duration
        t_back = t_sag + rng.uniform(0.2, 0.8) * duration
        jump = math.radians(rng.uniform(*jump_deg)) * rng.choice([-1.0, 1.0])
        t_jump = rng.uniform(0.05, 0.9) * duration
        steps = [(t_sag, "ug", sag_level), (t_jump, "theta_g", jump)]
        if t_back < duration:
            steps.append((t_back, "ug", ug0))
        schedules.append(Schedule(ug0, 0.0, steps, label=f"train-{k}"))
    return schedules


def evaluation_schedules(duration: float = 0.04) -> list[Schedule]:
    """Paper test set: from ug = 1.0, a sag to 0.4 p.u. at t = 0.02 s (OOD window
    0.02–0.04 s); the second trajectory adds an 8° phase jump at 0.008 s inside the
    IOD window (0–0.02 s) so that window tests something."""
    t_sag = 0.5 * duration
    return [
        Schedule(1.0, 0.0, [(t_sag, "ug", 0.4)], label="test-sag"),
        Schedule(1.0, 0.0, [(0.2 * duration, "theta_g", math.radians(8.0)), (t_sag, "ug", 0.4)],
                 label="test-jump-sag"),
    ]


def smallsignal_schedules(ug0: float = 0.8, dug: float = 0.01, dtheta: float = 0.01,
                          t_step: float = 0.005) -> list[Schedule]:
    """Small-signal set around ug0: ±dug steps of the grid voltage and ±dtheta (rad) steps of its phase."""
    return [
        Schedule(ug0, 0.0, [(t_step, "ug", ug0 + dug)], label="ss-ug+"),
        Schedule(ug0, 0.0, [(t_step, "ug", ug0 - dug)], label="ss-ug-"),
        Schedule(ug0, 0.0, [(t_step, "theta_g", dtheta)], label="ss-theta+"),
        Schedule(ug0, 0.0, [(t_step, "theta_g", -dtheta)], label="ss-theta-"),
    ]


def schedules_for(scenario: str, seed: int = 0, n_traj: int | None = None, duration: float | None = None):
    """Schedules of a named scenario (``train``, ``test`` or ``smallsignal``) and its duration."""
    if scenario == "train":
        duration = duration or 0.04
        return training_schedules(n_traj or 12, seed, duration), duration
    if scenario == "test":
        duration = duration or 0.04
        return evaluation_schedules(duration), duration
    if scenario == "smallsignal":
        duration = duration or 0.1
        schedules = smallsignal_schedules()
        return (schedules[:n_traj] if n_traj else schedules), duration
    raise ValueError(f"unknown scenario {scenario!r}; choose one of {SCENARIOS}")


def _with_effects(plant) -> str:
    effects = ", ".join(f"{name} {values}" for name, values in getattr(plant, "effects", {}).items())
    return f" with {effects}" if effects else ""


def _start(plant, index: int, schedule: Schedule) -> np.ndarray:
    """The rest state a record starts from; a settings error that names the record where there is none."""
    from .model import EquilibriumError

    try:
        return plant.equilibrium(schedule.ug0, schedule.theta0)
    except EquilibriumError as err:
        raise ParameterError(
            f"trajectory {index} starts at rest at ug0 = {schedule.ug0:.4g} p.u., theta0 = {schedule.theta0:.4g} "
            f"rad, and the plant{_with_effects(plant)} has no equilibrium there "
            f"(a limit too tight for that operating point?)") from err


def generate(plant, schedules: list[Schedule], duration: float, dt: float = 1.0 / SAMPLE_RATE_HZ,
             method: str = "rk4", metadata: dict | None = None) -> Dataset:
    """Simulate schedules from equilibrium; the dataset holds the 13 measured states.

    Returns
    -------
    Dataset
        Clean (noise-free) measurements with provenance metadata.

    Raises
    ------
    ParameterError
        A record that cannot start at rest, or a simulation that diverges: the plant's settings
        (its effects, most likely) do not fit the schedules.
    """
    n = int(round(duration / dt)) + 1
    x0 = np.stack([_start(plant, k, s) for k, s in enumerate(schedules)])
    inputs = np.stack([s.sample(n, dt) for s in schedules])
    try:
        states = simulate(plant, x0, inputs, dt, method=method)
    except FloatingPointError as err:
        raise ParameterError(f"the records of the plant{_with_effects(plant)} cannot be simulated: {err}") from err
    n_meas = len(plant.state_names)
    t = np.arange(n) * dt
    trajectories = [Trajectory(k, t.copy(), states[k, :, :n_meas], inputs[k]) for k in range(len(schedules))]
    meta = {
        "dt": dt,
        "units": {"time": "s", "angles": "rad", "other": "p.u.", "derivatives": "1/s"},
        "generator": f"pisml_ros {__version__} virtual HIL",
        "parameters": plant.params.to_dict(),
        "effects": plant.effects,
        "solver": method,
        "schedules": [dataclasses.asdict(s) for s in schedules],
    }
    meta.update(metadata or {})
    return Dataset(plant.state_names, plant.input_names, trajectories, meta)
