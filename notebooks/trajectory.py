"""A rotation trajectory from a gyroscope and noisy orientations: a cubic B-spline on SO(3)
(``so3_bspline``) fitted by gradient descent, its body rates in the loss, against scipy's
``RotationSpline`` through the noisy orientations.

The synthetic problem (float64, fixed seed, nothing downloaded):

- **Truth.** ``R(t) = exp(phi(t))``, the rotation vector ``phi`` a sum of sinusoids per axis
  (0.2-1.5 Hz, amplitudes 0.1-0.6 rad); its body angular velocity is exact,
  ``w_b(t) = J_r(phi(t)) phi'(t)`` (``so3_right_jacobian``).
- **Gyroscope** at 200 Hz: ``w_b + b + n``, white noise ``n`` of 0.05 rad/s per axis and a constant
  bias ``b`` of 0.01-0.02 rad/s per axis.
- **Orientations** at 10 Hz, 3 ms after the gyroscope's clock: ``R(t_m) exp(e_m)`` with ``e_m`` of
  2 degrees per axis.
- Timestamps are integer nanoseconds on the Unix epoch; every time the fit uses is made relative to the
  first gyroscope sample in integers, then converted to float64 seconds.

**Fit.** A uniform cumulative cubic B-spline with knots ``h = 0.1`` s apart, its control rotations
quaternion parameters ``(K, 4)`` moved by ``diffquat.torch.optim.RiemannianAdam`` (the bias a
Euclidean parameter beside them), minimising the negative log-likelihood of both sensors:
``sum_m |log(R_m^-1 R(t_m))|^2 / sigma_R^2 + sum_g |w(t_g) / h + b - g|^2 / sigma_g^2``, where
``so3_bspline`` gives ``R(u)`` and ``w = dw_b/du`` at ``u = t / h``. The same spline fitted to the
orientations alone, and ``scipy.spatial.transform.RotationSpline`` through the noisy orientations (an
interpolating cubic: its rate is the derivative of a curve through the noise), are the references.
Every method is scored against the truth at the gyroscope's instants within the orientations' span:
the RMS rotation angle (degrees) and the RMS norm of the angular velocity error (rad/s).

Run:  python notebooks/trajectory.py    (DIFFQUAT_SMALL=1: the small test-suite size)
"""

from __future__ import annotations

import argparse
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from _sizes import figure_dir, small_mode

import diffquat.numpy as dqn

# ---------------------------------------------------------------------------------------------------
# Settings

FUSED = "B-spline, orientations + gyro"
ORIENTATIONS_ONLY = "B-spline, orientations only"
ROTATION_SPLINE = "scipy RotationSpline"
GYRO = "gyro samples (bias removed)"

EPOCH_NS = 1_700_000_000_000_000_000  # the sensors' clock: nanoseconds since the Unix epoch


@dataclass(frozen=True)
class Settings:
    """Sizes and noise. The learning rate (radians per step on the control rotations, rad/s on the bias)
    decays exponentially to ``lr_decay`` times its start over ``steps``."""

    duration: float  # seconds of data
    steps: int
    gyro_hz: int = 200
    orientation_hz: int = 10
    orientation_offset_ns: int = 3_000_000  # the orientations' clock lags the gyroscope's by 3 ms
    knot_spacing: float = 0.1  # h, seconds
    gyro_noise: float = 0.05  # rad/s per axis
    gyro_bias: tuple[float, float, float] = (0.01, -0.02, 0.015)  # rad/s
    orientation_noise_deg: float = 2.0  # per axis
    lr: float = 0.05
    lr_decay: float = 0.01
    seed: int = 0


FULL = Settings(duration=20.0, steps=800)
SMALL = Settings(duration=4.0, steps=200)


def setup() -> None:
    """float64 throughout, one thread (a few thousand samples: more threads cost more than they give)."""
    import torch

    torch.set_default_dtype(torch.float64)
    torch.set_num_threads(1)


# ---------------------------------------------------------------------------------------------------
# The truth and the sensors (numpy, float64)


@dataclass(frozen=True)
class Truth:
    """``phi(t) = sum_j a_j sin(2 pi f_j t + p_j)`` per axis (``a``, ``f``, ``p`` of shape ``(J, 3)``),
    ``R(t) = exp(phi(t))``."""

    amplitude: np.ndarray
    frequency: np.ndarray
    phase: np.ndarray

    def rotation_vector(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``phi(t)`` and ``phi'(t)``, shape ``(T, 3)`` each, for times ``(T,)`` in seconds."""
        angle = 2 * np.pi * self.frequency * t[:, None, None] + self.phase
        phi = np.sum(self.amplitude * np.sin(angle), axis=-2)
        rate = np.sum(self.amplitude * 2 * np.pi * self.frequency * np.cos(angle), axis=-2)
        return phi, rate

    def rotation(self, t: np.ndarray) -> np.ndarray:
        """``R(t)``, shape ``(T, 3, 3)``."""
        return dqn.so3_exp(self.rotation_vector(t)[0])

    def angular_velocity(self, t: np.ndarray) -> np.ndarray:
        """The body angular velocity ``w_b = J_r(phi) phi'`` (rad/s), shape ``(T, 3)``: the derivative
        of ``exp(phi(t))`` is ``exp(phi) hat(J_r(phi) phi')``, ``J_r`` the right Jacobian."""
        phi, rate = self.rotation_vector(t)
        return np.einsum("...ij,...j->...i", dqn.so3_right_jacobian(phi), rate)


def make_truth(rng: np.random.Generator, terms: int = 3) -> Truth:
    """Three sinusoids per axis: amplitudes 0.6, 0.3 and 0.1 rad (scaled by 0.7-1.3), frequencies
    0.2-0.4, 0.5-0.9 and 1.0-1.5 Hz, random phases."""
    scale = np.array([0.6, 0.3, 0.1])[:terms, None] * rng.uniform(0.7, 1.3, size=(terms, 3))
    low, high = np.array([0.2, 0.5, 1.0])[:terms, None], np.array([0.4, 0.9, 1.5])[:terms, None]
    frequency = rng.uniform(low, high, size=(terms, 3))
    return Truth(scale, frequency, rng.uniform(0, 2 * np.pi, size=(terms, 3)))


@dataclass(frozen=True)
class Data:
    """What the sensors give: absolute integer timestamps and readings, and the truth to score against."""

    truth: Truth
    gyro_stamps_ns: np.ndarray  # (G,) int64
    gyro: np.ndarray  # (G, 3) rad/s, body frame, with noise and bias
    orientation_stamps_ns: np.ndarray  # (M,) int64
    orientations: np.ndarray  # (M, 3, 3) noisy rotations
    bias: np.ndarray  # (3,) the gyroscope's true bias

    def seconds(self, stamps_ns: np.ndarray) -> np.ndarray:
        """Times relative to the first gyroscope sample, float64 seconds: the difference is taken in
        integers (exact), and only then converted (float64 holds 1.7e18 ns to 256 ns, a relative
        time of seconds to well under a nanosecond)."""
        return (stamps_ns - self.gyro_stamps_ns[0]).astype(np.float64) * 1e-9


def make_data(settings: Settings) -> Data:
    """The truth, a gyroscope at ``gyro_hz`` from ``EPOCH_NS`` for ``duration`` seconds, orientations at
    ``orientation_hz`` from ``orientation_offset_ns`` later, within the same span."""
    s = settings
    rng = np.random.default_rng(s.seed)
    truth = make_truth(rng)
    g_step, m_step = 1_000_000_000 // s.gyro_hz, 1_000_000_000 // s.orientation_hz
    end = round(s.duration * 1e9)
    gyro_stamps = EPOCH_NS + np.arange(0, end + 1, g_step, dtype=np.int64)
    orientation_stamps = EPOCH_NS + np.arange(s.orientation_offset_ns, end + 1, m_step, dtype=np.int64)
    t_g = (gyro_stamps - EPOCH_NS).astype(np.float64) * 1e-9
    t_m = (orientation_stamps - EPOCH_NS).astype(np.float64) * 1e-9
    bias = np.asarray(s.gyro_bias)
    gyro = truth.angular_velocity(t_g) + bias + s.gyro_noise * rng.normal(size=(len(t_g), 3))
    noise = np.deg2rad(s.orientation_noise_deg) * rng.normal(size=(len(t_m), 3))
    orientations = dqn.so3_plus(truth.rotation(t_m), noise)
    return Data(truth, gyro_stamps, gyro, orientation_stamps, orientations, bias)


# ---------------------------------------------------------------------------------------------------
# The B-spline fit (torch)


@dataclass
class Fit:
    """A fitted spline: control rotations ``(K, 3, 3)``, knot spacing ``h`` (s), the spline's start
    (seconds, relative), the bias estimate, and the loss per step (with the time per step)."""

    control: np.ndarray
    h: float
    start: float
    bias: np.ndarray
    loss: list[float] = field(default_factory=list)
    seconds_per_step: float = 0.0

    def u(self, t: np.ndarray) -> np.ndarray:
        """Spline parameters for relative times in float64 seconds (computed in float64)."""
        return (t - self.start) / self.h

    def evaluate(self, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Rotations ``(T, 3, 3)`` and body angular velocities ``(T, 3)`` in rad/s at relative times."""
        rotation, omega, _ = dqn.so3_bspline(self.control, self.u(t))
        return rotation, omega / self.h


ORDER = 4  # cubic


def initial_control(data: Data, h: float, count: int) -> np.ndarray:
    """Control rotations ``(K, 3, 3)`` from the noisy orientations: control point ``j`` of a uniform
    cubic B-spline weighs most at ``u = j - 1``, so it starts at the orientation measured nearest to
    time ``(j - 1) h`` (clamped to the data)."""
    t_m = data.seconds(data.orientation_stamps_ns)
    times = (np.arange(count) - 1) * h
    nearest = np.abs(times[:, None] - t_m[None, :]).argmin(axis=1)
    return data.orientations[nearest]


def fit_bspline(data: Data, settings: Settings, use_gyro: bool = True) -> Fit:
    """The spline's control rotations (and the gyroscope's bias, with ``use_gyro``) by
    ``RiemannianAdam``, minimising the mean negative log-likelihood of the orientations
    (``|so3_minus(R(t_m), R_m)|^2 / sigma_R^2``) and, with ``use_gyro``, of the gyroscope
    (``|w(t_g) / h + b - g|^2 / sigma_g^2``), per sample. The spline starts at the first gyroscope
    sample and has one knot per ``h`` up to the last sample (``K = ceil(T / h) + 3`` control points)."""
    import torch

    import diffquat.torch as dq
    from diffquat.torch.optim import RiemannianAdam

    s, h = settings, settings.knot_spacing
    t_g, t_m = data.seconds(data.gyro_stamps_ns), data.seconds(data.orientation_stamps_ns)
    count = int(np.ceil(t_g[-1] / h - 1e-9)) + ORDER - 1
    # Relative times made in float64 (Data.seconds), divided by h in float64, then handed to torch.
    u_g, u_m = torch.from_numpy(t_g / h), torch.from_numpy(t_m / h)
    gyro = torch.from_numpy(data.gyro)
    measured = torch.from_numpy(data.orientations)
    sigma_r, sigma_g = np.deg2rad(s.orientation_noise_deg), s.gyro_noise

    q = torch.nn.Parameter(dq.matrix_to_quaternion(torch.from_numpy(initial_control(data, h, count))))
    bias = torch.nn.Parameter(torch.zeros(3))
    groups: list[dict[str, Any]] = [{"params": [q]}]
    if use_gyro:
        groups.append({"params": [bias], "manifold": "euclidean"})
    optimizer = RiemannianAdam(groups, lr=s.lr)
    schedule = torch.optim.lr_scheduler.ExponentialLR(optimizer, gamma=s.lr_decay ** (1.0 / s.steps))

    def loss() -> Any:
        control = dq.quaternion_to_matrix(q)
        rotation, _, _ = dq.so3_bspline(control, u_m)
        residual = dq.so3_minus(rotation, measured) / sigma_r  # (M, 3)
        total = (residual**2).sum(-1).mean()
        if use_gyro:
            _, omega, _ = dq.so3_bspline(control, u_g)
            total = total + (((omega / h + bias - gyro) / sigma_g) ** 2).sum(-1).mean()
        return total

    history, begin = [], time.perf_counter()
    for _ in range(s.steps):
        optimizer.zero_grad()
        value = loss()
        value.backward()
        optimizer.step()
        schedule.step()
        history.append(value.item())
    elapsed = time.perf_counter() - begin
    with torch.no_grad():
        history.append(float(loss()))
        control = dq.quaternion_to_matrix(q).numpy().copy()
    return Fit(control, h, 0.0, bias.detach().numpy().copy(), history, elapsed / s.steps)


# ---------------------------------------------------------------------------------------------------
# Scores


@dataclass(frozen=True)
class Estimate:
    """A method's rotations ``(T, 3, 3)`` and body rates ``(T, 3)`` (rad/s) at the scoring times."""

    label: str
    rotation: np.ndarray | None
    omega: np.ndarray


def scoring_times(data: Data) -> np.ndarray:
    """The gyroscope's instants (relative seconds) within the span of the orientations, where every
    method is defined (scipy's spline does not extrapolate)."""
    t_g, t_m = data.seconds(data.gyro_stamps_ns), data.seconds(data.orientation_stamps_ns)
    return t_g[(t_g >= t_m[0]) & (t_g <= t_m[-1])]


def rotation_spline(data: Data, t: np.ndarray) -> Estimate:
    """scipy's ``RotationSpline`` through the noisy orientations: rotations and rates (rad/s; scipy's
    rates are in the body frame, as diffquat's)."""
    from scipy.spatial.transform import Rotation, RotationSpline

    spline = RotationSpline(data.seconds(data.orientation_stamps_ns), Rotation.from_matrix(data.orientations))
    return Estimate(ROTATION_SPLINE, spline(t).as_matrix(), spline(t, 1))


def scores(data: Data, estimate: Estimate, t: np.ndarray) -> dict[str, float]:
    """RMS rotation error (degrees) and RMS angular velocity error (norm, rad/s) against the truth at
    times ``t``, with the largest of each."""
    omega_error = np.linalg.norm(estimate.omega - data.truth.angular_velocity(t), axis=-1)
    row = {
        "rate RMS (rad/s)": float(np.sqrt(np.mean(omega_error**2))),
        "rate max (rad/s)": float(omega_error.max()),
    }
    if estimate.rotation is not None:
        angle = np.rad2deg(dqn.matrix_geodesic_distance(estimate.rotation, data.truth.rotation(t)))
        row = {
            "rotation RMS (deg)": float(np.sqrt(np.mean(angle**2))),
            "rotation max (deg)": float(angle.max()),
        } | row
    return row


def measurement_scores(data: Data) -> dict[str, float]:
    """The sensors' own errors: the noisy orientations' RMS angle to the truth (degrees), and the
    gyroscope's RMS error (rad/s) with its true bias removed (the white noise alone) and with it kept."""
    t_m, t_g = data.seconds(data.orientation_stamps_ns), data.seconds(data.gyro_stamps_ns)
    angle = np.rad2deg(dqn.matrix_geodesic_distance(data.orientations, data.truth.rotation(t_m)))
    error = data.gyro - data.truth.angular_velocity(t_g)
    return {
        "orientations RMS (deg)": float(np.sqrt(np.mean(angle**2))),
        "gyro RMS, bias removed (rad/s)": float(np.sqrt(np.mean(np.sum((error - data.bias) ** 2, -1)))),
        "gyro RMS, raw (rad/s)": float(np.sqrt(np.mean(np.sum(error**2, -1)))),
    }


def truth_check(data: Data, dt: float = 1e-5) -> float:
    """How far the analytic truth rate ``J_r(phi) phi'`` is from the rate of the truth's rotations by
    central differences (``angular_velocity_from_quaternions`` over ``t +- dt/2``), at the orientation
    instants: the largest difference in rad/s."""
    t = data.seconds(data.orientation_stamps_ns)
    pair = np.stack([data.truth.rotation(t - dt / 2), data.truth.rotation(t + dt / 2)], axis=-3)
    numeric = dqn.angular_velocity_from_quaternions(dqn.matrix_to_quaternion(pair), dt)[..., 0, :]
    return float(np.abs(numeric - data.truth.angular_velocity(t)).max())


# ---------------------------------------------------------------------------------------------------
# Everything


@dataclass
class Result:
    settings: Settings
    data: Data
    fits: dict[str, Fit]
    estimates: dict[str, Estimate]
    table: list[dict[str, Any]]
    times: np.ndarray


def run_all(settings: Settings) -> Result:
    """The data, both B-spline fits, scipy's spline, and their scores at the scoring times."""
    setup()
    data = make_data(settings)
    t = scoring_times(data)
    fits = {
        FUSED: fit_bspline(data, settings),
        ORIENTATIONS_ONLY: fit_bspline(data, settings, use_gyro=False),
    }
    estimates = {label: Estimate(label, *fit.evaluate(t)) for label, fit in fits.items()}
    estimates[ROTATION_SPLINE] = rotation_spline(data, t)
    inside = np.isin(data.seconds(data.gyro_stamps_ns), t)
    estimates[GYRO] = Estimate(GYRO, None, data.gyro[inside] - data.bias)
    table = [{"method": label} | scores(data, e, t) for label, e in estimates.items()]
    return Result(settings, data, fits, estimates, table, t)


COLUMNS = ("method", "rotation RMS (deg)", "rotation max (deg)", "rate RMS (rad/s)", "rate max (rad/s)")


def render(rows: list[dict[str, Any]]) -> str:
    """The table as Markdown; a dash where a column does not apply."""

    def cell(x: Any) -> str:
        return "-" if x is None else f"{x:.3g}" if isinstance(x, float) else str(x)

    lines = ["| " + " | ".join(COLUMNS) + " |", "|" + "---|" * len(COLUMNS)]
    lines += ["| " + " | ".join(cell(row.get(c)) for c in COLUMNS) + " |" for row in rows]
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------
# The figure


STYLE: dict[str, dict[str, Any]] = {
    FUSED: {"color": "C1", "lw": 2.0},
    ORIENTATIONS_ONLY: {"color": "C2", "lw": 1.0, "ls": "--"},
    ROTATION_SPLINE: {"color": "C0", "lw": 1.0},
}


def block_rms(t: np.ndarray, error: np.ndarray, seconds: float) -> tuple[np.ndarray, np.ndarray]:
    """The RMS of ``error`` ``(T,)`` over consecutive blocks of ``seconds``, for a step plot: the blocks'
    starts and the last one's end, and their values with the last repeated."""
    block = np.floor((t - t[0]) / seconds).astype(int)
    count = np.bincount(block)
    keep = count > 0
    rms = np.sqrt(np.bincount(block, weights=error**2)[keep] / count[keep])
    starts = t[0] + seconds * np.nonzero(keep)[0]
    return np.append(starts, min(starts[-1] + seconds, t[-1])), np.append(rms, rms[-1])


def plot(result: Result, path: Path, window: tuple[float, float] = (1.0, 4.0), block: float = 0.5) -> Path:
    """Left: the body angular velocity per axis over ``window`` (seconds): the gyroscope's samples
    (bias not removed), each estimate, the truth drawn last. Right: the RMS angular velocity error
    and rotation error per method in blocks of ``block`` seconds over the whole run. Saved as a small
    PNG."""
    from matplotlib.figure import Figure

    t, data = result.times, result.data
    lo, hi = max(window[0], t[0]), min(window[1], t[-1])
    shown = (t >= lo) & (t <= hi)
    t_g = data.seconds(data.gyro_stamps_ns)
    g_shown = (t_g >= lo) & (t_g <= hi)
    truth = data.truth.angular_velocity(t)

    fig = Figure(figsize=(12, 7), dpi=72, layout="constrained")
    grid = fig.add_gridspec(3, 2, width_ratios=(3, 2))
    for axis in range(3):
        ax = fig.add_subplot(grid[axis, 0])
        ax.plot(
            t_g[g_shown], data.gyro[g_shown, axis], ".", color="0.6", ms=2.5, label="gyro samples (200 Hz)"
        )
        for label, style in STYLE.items():
            ax.plot(t[shown], result.estimates[label].omega[shown, axis], label=label, **style)
        ax.plot(t[shown], truth[shown, axis], color="k", lw=0.8, label="truth")
        ax.set_ylabel(f"$\\omega_{'xyz'[axis]}$ (rad/s, body)")
        if axis == 0:
            ax.set_title(f"body angular velocity, {lo:.0f}-{hi:.0f} s", fontsize=10)
            ax.legend(fontsize=7, loc="upper right", ncol=3)
    ax.set_xlabel("time (s)")
    rate_ax, angle_ax = fig.add_subplot(grid[:2, 1]), fig.add_subplot(grid[2, 1])
    rotations = data.truth.rotation(t)
    for label, style in STYLE.items():
        estimate = result.estimates[label]
        assert estimate.rotation is not None
        rate_ax.step(
            *block_rms(t, np.linalg.norm(estimate.omega - truth, axis=-1), block),
            where="post",
            label=label,
            **style,
        )
        angle = np.rad2deg(dqn.matrix_geodesic_distance(estimate.rotation, rotations))
        angle_ax.step(*block_rms(t, angle, block), where="post", **style)
    gyro_error = np.linalg.norm(result.estimates[GYRO].omega - truth, axis=-1)
    rate_ax.step(*block_rms(t, gyro_error, block), where="post", color="0.6", label=GYRO)
    rate_ax.set(yscale="log", ylabel="angular velocity error, RMS (rad/s)")
    rate_ax.set_title(f"errors against the truth, RMS per {block:g} s", fontsize=10)
    rate_ax.legend(fontsize=7, loc="center right")
    angle_ax.set(ylabel="rotation error, RMS (deg)", xlabel="time (s)", ylim=(0, None))
    fig.savefig(path, pil_kwargs={"optimize": True})
    return path


def run(settings: Settings | None = None, verbose: bool = True) -> Result:
    """Everything, printed, with the figure."""
    settings = settings or (SMALL if small_mode() else FULL)
    say = print if verbose else (lambda *a, **k: None)
    result = run_all(settings)
    say(render(result.table))
    path = plot(result, figure_dir() / "trajectory.png")
    say(f"figure saved to {os.path.relpath(path)}")
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.parse_args()
    print(f"size: {'small' if small_mode() else 'full'}")
    run()


if __name__ == "__main__":
    main()
