"""Where an agent's samples come from. The agent holds a SampleSource and never knows which one."""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from encoder_core.correction import BandedCorrection
from encoder_core.differential import BenchLocus
from encoder_core.methods import OursLsRef
from encoder_core.samples import Samples
from encoder_core.simulator import EncoderModel, bench_profile, cycle_profile, record, simulate, typical_drive


class SampleSource(ABC):
    """A stream of samples read in blocks of a given duration (seconds of the drive's clock)."""

    now: float = 0.0  # the drive's clock: end of the last block read

    @abstractmethod
    def read(self, duration_s: float) -> Samples | None:
        """The next block, or None when the source has ended."""


class SimulatedDrive(SampleSource):
    """A drive with its own encoder (drawn from a seed), going through heating and cooling between
    t_min and t_max, sampled at random positions. Runs as fast as the caller reads."""

    def __init__(
        self,
        seed: int,
        *,
        hours: float,
        sample_hz: float = 20.0,
        t_min: float = -40.0,
        t_max: float = 85.0,
        cycle_hours: float = 12.0,
        model: EncoderModel | None = None,
        knock_at_s: float | None = None,
        knock_fraction: float = 0.015,
    ):
        self.seed = seed
        self.model = model or drive_model(seed)
        # a knocked magnet (demo, drift monitor): from knock_at_s on, both offsets jump by knock_fraction
        # of the channel amplitude (1.5 % by default), along a direction drawn from the seed
        self.knock_at_s = knock_at_s
        direction = np.random.default_rng([seed, 5]).uniform(-np.pi, np.pi)
        jump = knock_fraction * 2.0 * self.model.hall_amplitude
        self.knocked = self.model.with_(
            offset_counts=(
                self.model.offset_counts[0] + jump * np.cos(direction),
                self.model.offset_counts[1] + jump * np.sin(direction),
            )
        )
        self.rng = np.random.default_rng([seed, 1])
        self.end_s = hours * 3600.0
        self.sample_s = 1.0 / sample_hz
        self.t_min, self.t_max, self.cycle_hours = t_min, t_max, cycle_hours
        self.now = 0.0
        self.die_temp: float | None = None

    def read(self, duration_s: float) -> Samples | None:
        if self.now >= self.end_s:
            return None
        hours = min(duration_s, self.end_s - self.now) / 3600.0
        profile = cycle_profile(
            hours,
            sample_s=self.sample_s,
            t_min=self.t_min,
            t_max=self.t_max,
            cycle_hours=self.cycle_hours,
            t0=self.now,
            rng=self.rng,
        )
        knocked = self.knock_at_s is not None and self.now >= self.knock_at_s
        samples, die = simulate(
            self.knocked if knocked else self.model,
            profile.t,
            profile.theta,
            profile.temp_c,
            self.rng,
            hours_offset=self.now / 3600.0,
            die_temp0=self.die_temp,
        )
        self.now += duration_s
        if die.size:
            self.die_temp = float(die[-1])
        samples.theta_ref = None  # a drive in the field has no reference angle
        return samples


class ReplaySource(SampleSource):
    """A recording replayed in blocks of its own time column: block k holds the samples of
    [t0 + k * duration, t0 + (k + 1) * duration). A stretch with no sample (the logger stopped, a rate slower than
    the window) is skipped to the next block that has one, so that no block is empty or taken from the next's."""

    def __init__(self, samples: Samples):
        self.samples = samples
        self.pos = 0
        self.t0 = float(samples.t[0]) if len(samples) else 0.0
        self.blocks = 0  # blocks of the grid from t0 passed, read or skipped
        self.now = self.t0

    def read(self, duration_s: float) -> Samples | None:
        if self.pos >= len(self.samples):
            return None
        t = self.samples.t
        # from t0 on each time, not summed: the grid does not drift at unix times (~1.7e9 s)
        first = max(self.blocks, int(np.floor((t[self.pos] - self.t0) / duration_s)))
        while True:  # the floor above may land one block short or long of t[pos] in rounding
            self.blocks = first + 1
            t_end = self.t0 + self.blocks * duration_s
            end = int(np.searchsorted(t, t_end, side="left"))
            if end > self.pos:
                break
            first += 1
        block = self.samples.subset(slice(self.pos, end))
        self.pos = end
        self.now = float(block.t[-1])
        return block


def drive_model(seed: int) -> EncoderModel:
    """The encoder of simulated device `seed`: a production part with its own drift, phase and harmonic."""
    return typical_drive(np.random.default_rng([seed, 0]))


def factory_calibration(model: EncoderModel, seed: int) -> BandedCorrection:
    """What the factory writes into a drive: a +20 °C bench sweep with a reference, fitted in closed form.
    It knows nothing of temperature, so it is the drive's correction at every temperature until the fleet
    service learns better."""
    rng = np.random.default_rng([seed, 2])
    sweep = record(model, bench_profile((20.0,), soak_s=0.0), rng)
    corr = OursLsRef().fit(sweep).correction_.bands[0]
    # the bench locus, as `encoder-fleet calibrate` writes it: what the fleet's refits measure drift against
    corr.bench_locus = BenchLocus.fit(sweep.theta_ref, sweep.d, sweep.q, corr.temp_c or 20.0).to_dict()
    return BandedCorrection([corr])


def evaluation_set(
    model: EncoderModel, seed: int, *, n: int = 20000, t_min: float = -40.0, t_max: float = 85.0, hours: float = 0.0
) -> Samples:
    """Truth for scoring a correction: random positions at settled temperatures across the cycle, at
    an age of `hours` of operation. Only the demo and tests use it; the agent and the service never see it."""
    rng = np.random.default_rng([seed, 3])
    temp = rng.uniform(t_min, t_max, n)
    theta = rng.uniform(0, 2 * np.pi, n)
    t = np.arange(n) * 1e-3  # a snapshot: the drive does not age during it
    samples, _ = simulate(model.with_(thermal_lag_tau_s=0.0), t, theta, temp, rng, hours_offset=hours)
    return samples
