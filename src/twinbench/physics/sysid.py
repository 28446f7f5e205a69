"""System identification (PhysTwin-style): fit a spring-mass object's physics to observed motion.

    result = identify(data, FitConfig(cma=CMAConfig(budget=200)))   # data: SysIdData (sysid_data.py)
    result.params, result.log_y, result.evals["final"].val_error

This module is the fit only; reading the input files, writing the identified object and the report
are construction tools (``twinbench.construct.sysid_io``, ``twinbench.construct.sysid_report``).

Stages (DESIGN section 4), each switchable for the ablation "without physics optimisation":

1. **Stage 1** (``stage1=True``): CMA-ES (``cma`` package) over the global parameters of
   :class:`GlobalParams` within :data:`DEFAULT_RANGES` (normalised to [0, 1], stiffness in log space);
   each evaluation builds the model and simulates every training frame (fast, graph-replayed path).
   Where the search shows the motion does not constrain a value measured in it, the measured value is
   kept (:func:`keep_unconstrained_guesses`; for the stiffness, stage 2 then holds its scale).
2. **Stage 2** (``stage2=True``): Adam on the per-spring log stiffness (object and control springs)
   through ``wp.Tape``, truncated to one frame: frame ``k`` is simulated from the simulated state of
   frame ``k - 1``, the loss's gradient w.r.t. the frame's final positions and velocities is injected as
   the adjoint of the taped frame's last state, Adam steps, and the detached state carries on. The
   stiffness is fitted per spatial region (``AdamConfig.regions``); the result says which regions the
   motion constrains (:func:`region_information`, ``SysIdResult.region_identifiability``).
3. **Stage 3** (``stage3=True``): CMA-ES again over the global parameters other than the spring rule,
   with stage 2's stiffness held.
4. **Stage 4** (``stage4=True``, off by default): CMA-ES over the stiffness regions' values and the contact
   and damping values together, the attachment held (:func:`stage4_cma`).

With control points whose attachment is searched, and a first run that tracks the training frames worse
than ``FitConfig.second_start_over_floor`` times the tracks' noise floor, stages 1-3 run from a second start
(stage 1 scoring the attachments before its search) and the run that tracks the training frames best is
kept (``FitConfig.attachment_starts``). With stages 1 and 2 off, the ``initial`` (hand-set) values are used as
they are and only evaluated.

Loss of frame ``k`` (PhysTwin's terms and weights 1, 1, 0.01):

* one-sided Chamfer: mean over the visible observed points of the squared distance to the nearest
  simulated surface particle;
* tracking: smooth-L1 (``beta``) of the tracked particles against their tracks, over the
  motion-valid tracks, divided by 3 * count;
* acceleration: smooth-L1 of the change of the per-frame velocity change
  ``(v_k - v_{k-1}) - (v_{k-1} - v_{k-2})`` over all particles, divided by 3 * P (from frame 2 on).

The control points' paths and the tool's poses are measurements: where they are noisy they are simulated
smoothed (``FitConfig.smooth_inputs``, ``sysid_guess.smoothed_inputs``; ``SysIdResult.inputs`` says what was
done); with the ground on, particles that lie below it at frame 0 are raised onto it
(``sysid_guess.grounded``).
The last ``validation_frames`` frames are never fitted; their *tracking error* (mean Euclidean
distance between tracked particles and motion-valid tracks, metres, simulating the whole sequence
from frame 0) is the validation figure of the report. Stage 2 also fits the contact parameters that
act (``AdamConfig.fit_contact``), in logit space.
"""

from __future__ import annotations

import contextlib
import math
import multiprocessing as mp
import os
import signal
import time
import warnings
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field, replace

import numpy as np
import warp as wp
from scipy.spatial import cKDTree

from twinbench._runtime import CPU_THREADS_ENV, quiet_warp, watch_parent

from .model import MIN_REST_LENGTH, RADIUS_SLACK, TIE_DECIMALS, ModelBuilder, SpringMassModel, radius_springs
from .params import SimParams
from .solver import SimulationDiverged, SpringMassSolver, check_divergence
from .sysid_data import SysIdData, SysIdFormatError

# ----------------------------------------------------------------------------------------------
# parameters and search space


@dataclass(frozen=True)
class GlobalParams:
    """The global (per-object) parameters of DESIGN section 4; defaults are PhysTwin's."""

    spring_Y: float = 3e4
    """stiffness of every spring (per unit strain) before stage 2"""
    spring_radius: float = 0.02
    """object springs join particles within this radius (ignored with explicit springs)"""
    spring_max_neighbors: int = 30
    control_radius: float = 0.04
    """control points attach to the particles within this radius"""
    control_max_neighbors: int = 50
    ground_restitution: float = 0.5
    ground_friction: float = 0.3
    object_restitution: float = 0.7
    """self-collision restitution (used when self-collision is on)"""
    object_friction: float = 0.3
    collision_dist: float = 0.02
    drag_damping: float = 3.0
    dashpot_damping: float = 100.0
    tool_friction: float = 0.3
    """friction between a kinematic tool (``SysIdData.tool_*``) and the object (twinbench's tool default)"""
    tool_restitution: float = 0.0

    def sim_params(self, base: SimParams) -> SimParams:
        """``base`` with this object's contact and damping values."""
        return replace(base, ground_restitution=self.ground_restitution, ground_friction=self.ground_friction,
                       object_restitution=self.object_restitution, object_friction=self.object_friction,
                       collision_dist=self.collision_dist, drag_damping=self.drag_damping,
                       dashpot_damping=self.dashpot_damping)


@dataclass(frozen=True)
class SearchRange:
    """A stage-1 search interval; ``log`` searches log(value), ``integer`` rounds."""

    lo: float
    hi: float
    log: bool = False
    integer: bool = False

    def decode(self, u: float) -> float | int:
        """Value at the normalised position ``u`` in [0, 1] (clipped)."""
        u = min(max(float(u), 0.0), 1.0)
        if self.log:
            val = math.exp(math.log(self.lo) + u * (math.log(self.hi) - math.log(self.lo)))
        else:
            val = self.lo + u * (self.hi - self.lo)
        return int(round(val)) if self.integer else val

    def encode(self, value: float) -> float:
        value = min(max(float(value), self.lo), self.hi)
        if self.log:
            return (math.log(value) - math.log(self.lo)) / (math.log(self.hi) - math.log(self.lo))
        return (value - self.lo) / (self.hi - self.lo)


DEFAULT_RANGES: dict[str, SearchRange] = {
    "spring_Y": SearchRange(10.0, 1e5, log=True),
    "spring_radius": SearchRange(0.01, 0.05),
    "spring_max_neighbors": SearchRange(10, 50, integer=True),
    "control_radius": SearchRange(0.01, 0.08),
    "control_max_neighbors": SearchRange(1, 80, integer=True),
    "ground_restitution": SearchRange(0.0, 1.0),
    "ground_friction": SearchRange(0.0, 2.0),
    "object_restitution": SearchRange(0.0, 1.0),
    "object_friction": SearchRange(0.0, 2.0),
    "collision_dist": SearchRange(0.005, 0.05),
    "drag_damping": SearchRange(0.0, 20.0),
    "dashpot_damping": SearchRange(0.0, 200.0),
    "tool_friction": SearchRange(0.0, 2.0),
    "tool_restitution": SearchRange(0.0, 1.0),
}


def within_ranges(params: GlobalParams, names, ranges: dict[str, SearchRange]) -> GlobalParams:
    """``params`` with each of ``names`` that lies outside its search range moved to the range's nearest
    end (a hand-set start outside a range the user narrowed: the search must not return it)."""
    out = {n: min(max(getattr(params, n), ranges[n].lo), ranges[n].hi) for n in names
           if not ranges[n].lo <= getattr(params, n) <= ranges[n].hi}
    return replace(params, **out) if out else params


RULE_NAMES = ("spring_radius", "spring_max_neighbors")
"""the object-spring rule's parameters (searched only without explicit springs)"""


def applicable_parameters(data: SysIdData, base: SimParams) -> tuple[str, ...]:
    """The global parameters that change the simulation of ``data``: topology rules only without
    explicit springs, control rules only with control points, self-contact only with self-collision,
    ground contact only with the ground on, the tool's contact only with a tool."""
    names = ["spring_Y"]
    if data.springs is None:
        names += RULE_NAMES
    if data.num_controls:
        names += ["control_radius", "control_max_neighbors"]
    if base.ground:
        names += ["ground_restitution", "ground_friction"]
    if base.self_collision:
        names += ["object_restitution", "object_friction", "collision_dist"]
    if data.has_tool:
        names += ["tool_restitution", "tool_friction"]
    return tuple(names + ["drag_damping", "dashpot_damping"])


PARAM_LIMITS: dict[str, tuple[float, float, bool]] = {
    "spring_Y": (0.0, 1e12, True), "spring_radius": (0.0, 10.0, True), "control_radius": (0.0, 10.0, True),
    "spring_max_neighbors": (1, 1_000, False), "control_max_neighbors": (1, 1_000, False),
    **{f"{k}_restitution": (0.0, 1.0, False) for k in ("ground", "object", "tool")},
    **{f"{k}_friction": (0.0, 2.0, False) for k in ("ground", "object", "tool")},
    "collision_dist": (0.0, 1.0, False), "drag_damping": (0.0, 1e4, False),
    "dashpot_damping": (0.0, 1e6, False),
}
"""what each global parameter can be, (low, high, low excluded): the bounds of ``--initial.*`` values and of
``--cma.ranges`` (the contact kernels clamp restitution to [0, 1] and friction to [0, 2], so a value past
those would be reported but never simulated)"""


def parse_ranges(overrides: tuple[str, ...] | list[str]) -> dict[str, SearchRange]:
    """DEFAULT_RANGES updated by ``"name=lo:hi"`` strings (the scale, log or integer, is kept), each within
    the parameter's ``PARAM_LIMITS``."""
    ranges = dict(DEFAULT_RANGES)
    for item in overrides:
        name, sep, rest = item.partition("=")
        lo, sep2, hi = rest.partition(":")
        if not sep or not sep2 or name not in ranges:
            raise ValueError(f"range override {item!r} must look like NAME=LO:HI with NAME one of "
                             f"{sorted(ranges)}")
        try:
            lo_f, hi_f = float(lo), float(hi)
        except ValueError:
            raise ValueError(f"range override {item!r}: LO and HI must be numbers") from None
        old = ranges[name]
        if not (math.isfinite(lo_f) and math.isfinite(hi_f) and hi_f > lo_f) or (old.log and lo_f <= 0):
            need = " and LO > 0 (log scale)" if old.log else ""
            raise ValueError(f"range override {item!r}: need finite LO < HI{need}")
        low, high, open_ = PARAM_LIMITS[name]
        if lo_f < low or (open_ and lo_f == low) or hi_f > high:
            bound = f"({low:g}, {high:g}]" if open_ else f"[{low:g}, {high:g}]"
            contact = name.endswith(("friction", "restitution"))
            why = " (the contact kernels clamp it there)" if contact else ""
            raise ValueError(f"range override {item!r}: {name} must lie in {bound}{why}")
        ranges[name] = SearchRange(lo_f, hi_f, old.log, old.integer)
    return ranges


# ----------------------------------------------------------------------------------------------
# configuration


@dataclass(frozen=True)
class LossWeights:
    chamfer: float = 1.0
    track: float = 1.0
    acc: float = 0.01
    beta: float = 1.0
    """smooth-L1 transition (m, or m/s for the acceleration term); 1.0 as fvcore's default in PhysTwin"""


@dataclass(frozen=True)
class CMAConfig:
    """Stage 1 (CMA-ES) settings."""

    budget: int = 150
    """maximum number of evaluations (each simulates every training frame) of one search; with the spring
    rule's ``topologies``, of each set's start and of its search"""
    popsize: int = 0
    """population per generation; 0 = cma's default 4 + 3 ln(n)"""
    sigma0: float = 0.25
    """initial step size in normalised [0, 1] units"""
    search: tuple[str, ...] = ()
    """parameters to search (empty = every applicable one, see applicable_parameters)"""
    ranges: tuple[str, ...] = ()
    """range overrides as NAME=LO:HI (e.g. spring_Y=100:20000)"""
    seed: int = 0
    """random seed (cma receives seed + 1: its 0 means a time-based seed)"""
    patience: int = 3
    """stop after this many CMA-ES generations without a 1 % improvement of the best loss (0 = use the
    whole budget)"""
    topologies: int = 8
    """where the spring rule is searched (no explicit springs): the distinct spring sets that its radius
    makes over the radius range (at the start's neighbour cap, :func:`rule_topologies`), at most this many,
    spread over their spring counts, each scored from the start (its stiffness scan and attachments); then
    CMA-ES searches the other parameters on the best ``finalists`` of them with the rule held, and the best
    is kept (:func:`stage1_topologies`). The loss is flat in the radius between the radii where a
    neighbour shell joins, so a search that moves the radius with the rest stops on the first set that it
    meets (the PhysTwin-like rope: a 1.39 cm ladder, 58 springs; BENCHMARKS.md). 0 = the radius and the
    cap searched by CMA-ES with the rest"""
    finalists: int = 8
    """of the spring rule's ``topologies``, how many CMA-ES searches (the best by their starts' loss; on the
    PhysTwin-like rope the start's loss ranked the set that the searches find best fifth of seven, so by
    default every one is searched)"""
    workers: int = 1
    """processes that score a generation's candidates at once (spawned, each simulating on one core:
    CandidatePool), e.g. the machine's cores, at most the population; it serves stages 1, 3 and 4.
    1 = one after another in this process. The fit is the same either way"""


@dataclass(frozen=True)
class AdamConfig:
    """Stage 2 (Adam on per-spring log Y through wp.Tape, one frame at a time) settings."""

    epochs: int = 20
    """passes over the training frames (one Adam step per frame)"""
    lr: float = 0.02
    """step in log Y per frame (20 epochs of 24 frames can move a spring by a factor e^10)"""
    betas: tuple[float, float] = (0.9, 0.99)
    eps: float = 1e-12
    """Adam epsilon (the loss is in m^2: its gradients are small)"""
    y_min: float = 1.0
    """per-spring stiffness bounds (projected after each step); stage 2 also keeps every spring within
    ``window`` of stage 1's stiffness, and with automatic substeps simulates stably at the upper bound"""
    y_max: float = 1e5
    window: float = 10.0
    """per-spring stiffness stays within [Y1 / window, Y1 * window] of stage 1's global Y1 (0 = off)"""
    regions: int = 4
    """stiffness is fitted per spatial region (k-means of the springs' midpoints; control springs one
    more): per-spring values are rarely supported by a few dozen noisy frames, and on the held-out family
    (BENCHMARKS.md) 4 regions ranked the truth's stiffness pattern better than 6 or 8 (each region's value
    is constrained by more of the motion); 0 = per spring"""
    contact_after: float = 0.5
    """fraction of the epochs that fit stiffness alone before the contact parameters join (their
    gradients are noisy until the stiffness explains the motion)"""
    fit_contact: bool = True
    """also fit the contact parameters that act (ground restitution and friction with the ground on,
    object-object ones with self-collision); off: keep them from stage 1 or as given"""
    contact_lr: float = 0.05
    """Adam step for the contact parameters, in logit space (restitution = sigmoid(u), friction =
    2 sigmoid(u)): bounded, and a step moves a mid-range value by about lr / 4 of its range"""
    acc_share: float = 0.1
    """the acceleration term's weight is lowered (never raised) so that at stage 2's start the term is at
    most this share of the Chamfer + tracking terms: it regularises, it cannot dominate (0 = as given)"""
    epoch_by_selection: bool = False
    """keep the epoch with the lowest tracking error on the selection frames (``FitConfig.select_frames``)
    instead of the lowest fitted loss (the selection frames choose between the stages either way)"""
    patience: int = 3
    """epochs without a 0.5 % improvement of the best training loss before the stiffness-only phase ends
    (the contact parameters join early) or, once they have joined, before stopping (0 = all epochs)"""


@dataclass(frozen=True)
class FitConfig:
    """The fit's settings: which stages run, their settings, the loss weights and the simulation's time
    step (``twinbench sysid``'s config extends this with the input and output paths)."""

    device: str = "cpu"
    stage1: bool = True
    """run CMA-ES over the global parameters (off: use the initial values as given)"""
    stage2: bool = True
    """run Adam on per-spring stiffness (off: one global stiffness)"""
    initial: GlobalParams = GlobalParams()
    """starting point of stage 1, or the hand-set values when stage 1 is off"""
    cma: CMAConfig = CMAConfig()
    adam: AdamConfig = AdamConfig()
    weights: LossWeights = LossWeights()
    dt: float = 0.0
    """simulation substep (s); 0 = automatic (see substeps)"""
    substeps: int = 0
    """substeps per frame; 0 = round(1 / (fps * dt)) (667 at PhysTwin's dt 5e-5 and 30 fps), or with dt 0
    too, automatic: the fewest that are stable (``stable_substeps``) for each stage-1 candidate's stiffness
    and dashpot, and for stage 2's upper stiffness bound"""
    select_frames: float = 0.0
    """share of the training frames, the last ones, held out from fitting to choose between the stages
    (the selection frames: the stage with the lowest tracking error on them is kept; 0.2 is a good value);
    the validation frames never fit nor choose. 0 = every training frame is fitted and the last stage run
    is kept (on the held-out family, holding out 20 % cost more accuracy than the choice gained: short
    sequences lose their most informative frames)"""
    keep_guess: float = 0.1
    """where stage 1's search shows that the motion does not constrain a parameter that was measured in it
    (``guess``; see :func:`identifiability`), the measured value replaces stage 1's best point when that
    costs at most this share of training loss (:func:`keep_unconstrained_guesses`); 0 = off"""
    stage3: bool = True
    """after stage 2, CMA-ES again over the global parameters other than the spring rule (control
    attachment, contact, damping) with stage 2's stiffness held: stage 1 chose them under one uniform
    stiffness, which they partly stand in for (on the held-out family this lowered the validation error
    and the friction error where the motion slides; see BENCHMARKS.md)"""
    stage3_budget: int = 150
    """stage 3's evaluations, all used (its CMA-ES otherwise as ``cma``: step size, seed; the gains
    come slowly there, so ``cma.patience`` stopped it too early on the held-out family)"""
    stage4: bool = False
    """after stage 3 (or 2), CMA-ES over the stiffness regions' values (each within a factor
    ``STAGE4_SPAN`` of its fitted value, the control springs one more) and the contact and damping
    values together, the attachment held: stages 2 and 3 each fit their part with the other held, and
    where the two are coupled (a softer object held by more particles, or more damped) neither moves
    alone (:func:`stage4_cma`)"""
    stage4_budget: int = 200
    """stage 4's evaluations, all used"""
    rounds: int = 1
    """times stages 2 and 3 run, each round from the last one's stiffness pattern and global values:
    each stage fits its part with the other held, and the parts are coupled (the earlier rounds' stages
    are kept as ``stage2_round1``, ...; 2 ranked the family's stiffness better at 2.3x the time, but not
    every case: see BENCHMARKS.md)"""
    attachment_starts: bool = True
    """with control points whose attachment stage 1 searches, run the stages a second time where the first
    run tracks poorly (``second_start_over_floor``), stage 1 then scoring the control attachments
    (:func:`attachment_families`) before its CMA-ES rather than after; keep the run whose result tracks
    the training frames best (the attachment changes the motion in steps: either start can
    lead a later stage into the better basin, and on the held-out family neither is better on every case;
    the training tracking error picked the one with the lower validation error in 12 of the 14 cases of
    seeds 0-5 where both ran, the others a tie and a motion chaotic in the time step). Off: one run (half
    the time)"""
    second_start_over_floor: float = 1.5
    """the second start runs only when the first run's training tracking error exceeds this multiple of the
    tracks' noise floor (the error a perfect model would have: 1.596 x the per-axis noise estimated from
    the tracks, ``sysid_guess.track_noise``): a fit at the floor has nothing left to gain; 0 = always"""
    guess: bool = True
    """stage 1 starts from physically scaled guesses computed from the data (stiffness from the control
    force and strain, friction from sliding, restitution from bounces: ``physics.sysid_guess``) where the
    motion shows them; off: from the ``initial`` values"""
    smooth_inputs: bool = True
    """simulate the control points' paths and the tool's poses smoothed where their measured noise is at
    least 0.05 mm per axis (a smoothing spline per coordinate, chosen by cross-validation; see
    sysid_guess.smoothed_inputs); off: exactly as given"""
    ground: bool = True
    self_collision: bool = False
    mesh_margin: float = 0.005
    """contact distance of a tool's mesh (``SysIdData.tool_*``); give the twin's ``sim.mesh_margin``, so the
    fitted tool friction is the one its contact model needs"""
    progress: bool = True

    @property
    def auto_substeps(self) -> bool:
        return not self.substeps and not self.dt

    def check(self) -> None:
        """Every option within its range, else a ValueError naming the option as the CLI spells it."""
        def need(name: str, value, lo: float, hi: float, integer: bool = False,
                 lo_open: bool = False) -> None:
            ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value) \
                and (value > lo if lo_open else value >= lo) and value <= hi \
                and (not integer or float(value).is_integer())
            if not ok:
                kind = "an integer" if integer else "a number"
                bound = f"({lo}, {hi}]" if lo_open else f"[{lo}, {hi}]"
                raise ValueError(f"--{name.replace('_', '-')}: expected {kind} in {bound}, got {value!r}")

        need("dt", self.dt, 0.0, 0.1)
        need("select_frames", self.select_frames, 0.0, 0.5)
        need("keep_guess", self.keep_guess, 0.0, 10.0)
        need("substeps", self.substeps, 0, 100_000, integer=True)
        c, a, w, i = self.cma, self.adam, self.weights, self.initial
        need("cma.budget", c.budget, 1, 100_000, integer=True)
        need("stage3_budget", self.stage3_budget, 1, 100_000, integer=True)
        need("stage4_budget", self.stage4_budget, 1, 100_000, integer=True)
        need("rounds", self.rounds, 1, 20, integer=True)
        need("cma.popsize", c.popsize, 0, 1_000, integer=True)
        need("cma.sigma0", c.sigma0, 0.0, 1.0, lo_open=True)
        need("cma.patience", c.patience, 0, 100_000, integer=True)
        need("cma.seed", c.seed, 0, 2**31 - 2, integer=True)
        need("cma.workers", c.workers, 1, 1_000, integer=True)
        need("cma.topologies", c.topologies, 0, 1_000, integer=True)
        need("cma.finalists", c.finalists, 1, 1_000, integer=True)
        need("adam.epochs", a.epochs, 0, 100_000, integer=True)
        need("adam.lr", a.lr, 0.0, 10.0)
        need("adam.contact_lr", a.contact_lr, 0.0, 10.0)
        need("adam.eps", a.eps, 0.0, 1.0, lo_open=True)
        for k, beta in enumerate(a.betas):
            need(f"adam.betas[{k}]", beta, 0.0, 1.0)
        need("adam.y_min", a.y_min, 0.0, 1e12, lo_open=True)
        need("adam.y_max", a.y_max, a.y_min, 1e12, lo_open=True)
        need("adam.window", a.window, 0.0, 1e6)
        need("adam.regions", a.regions, 0, 100_000, integer=True)
        need("adam.contact_after", a.contact_after, 0.0, 1.0)
        need("adam.acc_share", a.acc_share, 0.0, 1.0)
        need("adam.patience", a.patience, 0, 100_000, integer=True)
        for name in ("chamfer", "track", "acc"):
            need(f"weights.{name}", getattr(w, name), 0.0, 1e6)
        need("weights.beta", w.beta, 0.0, 1e3, lo_open=True)
        for name, (lo, hi, lo_open) in PARAM_LIMITS.items():
            need(f"initial.{name}", getattr(i, name), lo, hi, integer=isinstance(lo, int), lo_open=lo_open)
        need("mesh_margin", self.mesh_margin, 0.0, 1.0)

    def base_params(self, fps: float, substeps: int = 0) -> SimParams:
        """The simulation settings; with automatic substeps, ``substeps`` (else PhysTwin's 667)."""
        if self.auto_substeps:
            n = substeps or round(1.0 / (fps * 5e-5))
            return SimParams(dt=1.0 / (fps * n), substeps=n, ground=self.ground,
                             self_collision=self.self_collision, mesh_margin=self.mesh_margin)
        if not self.substeps and 1.0 / (fps * self.dt) > 100_000.5:  # --substeps itself is range-checked
            raise ValueError(f"--dt {self.dt}: gives {1.0 / (fps * self.dt):.3g} substeps per frame at "
                             f"{fps:g} fps (at most 100000); give a larger --dt, or 0 for automatic substeps")
        n = self.substeps or max(1, round(1.0 / (fps * self.dt)))
        dt = self.dt or 1.0 / (fps * n)
        return SimParams(dt=dt, substeps=n, ground=self.ground, self_collision=self.self_collision,
                         mesh_margin=self.mesh_margin)


# ----------------------------------------------------------------------------------------------
# model and loss


def build_model(data: SysIdData, params: GlobalParams, base: SimParams, device: str = "cpu", *,
                requires_grad: bool = False, log_y: np.ndarray | None = None,
                hold: tuple[np.ndarray, float] | None = None) -> SpringMassModel:
    """The spring-mass model of ``data`` under ``params`` (springs by rule or explicit, control points
    attached at their frame-0 positions, the tool as a kinematic mesh at its frame-0 pose, every spring at
    ``params.spring_Y`` unless ``log_y``, or with
    ``hold`` = (object springs' log Y, one log Y for the control springs, however many the control rule
    gives))."""
    b = ModelBuilder(params.sim_params(base))
    mass = 1.0 if data.masses is None else data.masses
    if data.springs is not None:
        b.add_body(data.particles, springs=data.springs, rest_lengths=data.rest_lengths,
                   spring_Y=params.spring_Y, mass=mass)
    else:
        b.add_body(data.particles, radius=params.spring_radius,
                   max_neighbors=int(params.spring_max_neighbors), spring_Y=params.spring_Y, mass=mass)
    if data.num_controls:
        b.add_control_points(data.controls[0], radius=params.control_radius,
                             max_neighbors=int(params.control_max_neighbors), spring_Y=params.spring_Y)
    if data.has_tool:
        b.add_kinematic_mesh(data.tool_path()[0], data.tool_faces, restitution=params.tool_restitution,
                             friction=params.tool_friction)
    model = b.finalize(device, requires_grad=requires_grad)
    if hold is not None:
        obj_y, ctl_y = hold
        log_y = np.concatenate([obj_y, np.full(model.num_springs - len(obj_y), ctl_y)]).astype(np.float32)
    if log_y is not None:
        model.set_spring_log_y(log_y)
    return model


def held_stiffness(model: SpringMassModel) -> tuple[np.ndarray, float]:
    """``model``'s stiffness as :func:`build_model`'s ``hold``: the object springs' log Y and the control
    springs' mean log Y (0 without control springs)."""
    ly = model.log_y_np.astype(np.float64)
    n = model.num_object_springs
    return ly[:n], float(ly[n:].mean() if len(ly) > n else 0.0)


def stability_rates(model: SpringMassModel, y_max: float, dashpot: float) -> tuple[float, float]:
    """Bounds (1/s) on the fastest stiffness and dashpot rates of ``model`` with every spring at stiffness
    ``y_max`` and the dashpot at ``dashpot``: per particle (Gershgorin) omega^2 <= 2 sum(Y / L) / m and
    gamma <= 2 n c / m over its n springs; returns (omega, gamma), each the largest over the particles."""
    n = model.num_particles
    sp = model.springs_np.astype(np.int64)
    k = float(y_max) / np.maximum(model.rest_lengths_np.astype(np.float64), 1e-6)
    stiff = np.zeros(n)
    count = np.zeros(n)
    for end in (0, 1):
        ok = sp[:, end] < n
        np.add.at(stiff, sp[ok, end], k[ok])
        np.add.at(count, sp[ok, end], 1.0)
    m = model.masses_np.astype(np.float64)[:n]
    return (math.sqrt(float(np.max(2.0 * stiff / m))),
            float(np.max(2.0 * count * max(float(dashpot), 0.0) / m)))


def stable_substeps(model: SpringMassModel, y_max: float, dashpot: float, fps: float,
                    max_substeps: int = 2000) -> int:
    """The fewest substeps per frame (dt = 1 / (fps substeps)) at which the semi-implicit Euler step is
    stable, with margin, at the rates of `stability_rates`. A mode x'' = -omega^2 x - gamma x' under this
    step (velocity first, the dashpot on the old velocity) is stable when (dt omega)^2 + 2 dt gamma < 4 (its
    matrix has determinant 1 - dt gamma and trace 2 - (dt omega)^2 - dt gamma); the margin is that of
    dt omega <= 1.5 undamped: (dt omega)^2 + 2 dt gamma <= 2.25, so dt gamma <= 1.125 with no stiffness.
    (A bound dt (omega + gamma / 2) <= 1.5 allowed dt gamma up to 3, past the limit 2 where the dashpot
    dominates.)"""
    omega, gamma = stability_rates(model, y_max, dashpot)
    dt = 2.25 / max(gamma + math.sqrt(gamma * gamma + 2.25 * omega * omega), 1e-9)  # the bound's root
    return int(min(max(math.ceil(1.0 / (fps * dt)), 1), max_substeps))


def _smooth_l1(d: np.ndarray, beta: float) -> tuple[np.ndarray, np.ndarray]:
    """Elementwise smooth-L1 value and derivative (fvcore convention)."""
    a = np.abs(d)
    val = np.where(a < beta, 0.5 * d * d / beta, a - 0.5 * beta)
    return val, np.clip(d / beta, -1.0, 1.0)


class SequenceLoss:
    """Per-frame loss of simulated positions/velocities against ``data`` and its gradient."""

    def __init__(self, data: SysIdData, weights: LossWeights = LossWeights()):
        self.data = data
        self.w = weights
        self.surface = (np.arange(data.num_particles) if data.surface_indices is None
                        else data.surface_indices)

    def frame(self, k: int, x: np.ndarray, v: np.ndarray, prev_v: np.ndarray | None = None,
              prev_acc: np.ndarray | None = None, grad: bool = False):
        """Loss terms of frame ``k`` (dict: chamfer, track, acc, total) and, with ``grad``, the
        gradients w.r.t. ``x`` and ``v`` (float64 arrays shaped like them)."""
        d, w = self.data, self.w
        x = np.asarray(x, np.float64)
        v = np.asarray(v, np.float64)
        gx = np.zeros_like(x) if grad else None
        gv = np.zeros_like(v) if grad else None
        # one-sided Chamfer: observed (visible) -> nearest simulated surface particle
        obs = d.observed[k][d.visibility[k]]
        surf = x[self.surface]
        _, nn = cKDTree(surf).query(obs)
        diff = surf[nn] - obs
        chamfer = w.chamfer * float(np.mean(np.sum(diff * diff, axis=1)))
        if grad:
            np.add.at(gx, self.surface[nn], 2.0 * w.chamfer / obs.shape[0] * diff)
        # tracking
        valid = d.motion_valid[k]
        track = 0.0
        if valid.any():
            idx = d.tracked_indices[valid]
            val, der = _smooth_l1(x[idx] - d.tracked[k][valid], w.beta)
            scale = w.track / (3.0 * idx.size)
            track = scale * float(val.sum())
            if grad:
                gx[idx] += scale * der
        # acceleration smoothness
        acc = 0.0
        if prev_v is not None and prev_acc is not None and w.acc:
            val, der = _smooth_l1((v - prev_v) - prev_acc, w.beta)
            scale = w.acc / (3.0 * v.shape[0])
            acc = scale * float(val.sum())
            if grad:
                gv += scale * der
        terms = {"chamfer": chamfer, "track": track, "acc": acc, "total": chamfer + track + acc}
        return (terms, gx, gv) if grad else terms

    def track_error(self, k: int, x: np.ndarray) -> float:
        """Mean distance (m) between tracked particles and their motion-valid tracks; NaN if none."""
        valid = self.data.motion_valid[k]
        if not valid.any():
            return float("nan")
        idx = self.data.tracked_indices[valid]
        diff = np.asarray(x, np.float64)[idx] - self.data.tracked[k][valid]
        return float(np.mean(np.linalg.norm(diff, axis=1)))


@dataclass
class SequenceEval:
    """Fast-path rollout of a model over the data: per-frame loss and tracking error (index = frame)."""

    loss: np.ndarray
    track_error: np.ndarray
    train_loss: float
    train_error: float
    val_error: float
    diverged: bool = False
    terms: dict[str, float] = field(default_factory=dict)
    """each loss term (chamfer, track, acc) averaged over the training frames"""


def set_frame_inputs(model: SpringMassModel, ctl, controls: np.ndarray, tool: np.ndarray | None,
                     k: int) -> None:
    """Frame k's kinematic inputs in ``ctl``: the control points from ``controls[k-1]`` to ``controls[k]``
    and the tool (``tool``: its world vertices per frame, ``SysIdData.tool_path``) from frame k-1 to k."""
    if controls.shape[1]:
        ctl.set_control_points(controls[k - 1], controls[k])
    if tool is not None:
        mesh = next(i for i, m in enumerate(model.meshes) if m.kinematic)
        ctl.set_kinematic_mesh(mesh, tool[k - 1], tool[k])


SPLIT_PAYBACK_FRAMES = 250
"""a rollout shorter than this runs on one core: a solver that splits its frames over two processes
(physics.split) starts its helper on its first frame, about 2-2.7 s, and saves about 9 ms a frame after
(a 1,014-particle toy at 300 substeps), so a sysid candidate's 30-90 frames took 3x as long split"""


def rollout(model: SpringMassModel, controls: np.ndarray, frames: int, solver: SpringMassSolver | None = None,
            tool: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Simulate frames 1..``frames`` (fast path) with the control points moving from ``controls[k-1]``
    to ``controls[k]`` and the tool (``SysIdData.tool_path()``, if any) from its frame k-1 to frame k
    vertices in frame k; returns positions and velocities (frames + 1, P, 3). Raises SimulationDiverged.
    Without ``solver``, a new one (on one core under ``SPLIT_PAYBACK_FRAMES`` frames)."""
    solver = solver or SpringMassSolver(model, threads=1 if frames < SPLIT_PAYBACK_FRAMES else None)
    state, ctl = model.state(requires_grad=False), model.control()
    xs = np.empty((frames + 1, model.num_particles, 3), np.float32)
    vs = np.empty_like(xs)
    xs[0], vs[0] = state.numpy()
    for k in range(1, frames + 1):
        set_frame_inputs(model, ctl, controls, tool, k)
        solver.simulate_frame(state, ctl)
        xs[k], vs[k] = state.numpy()
    return xs, vs


def evaluate(model: SpringMassModel, data: SysIdData, loss: SequenceLoss, *, frames: int | None = None,
             solver: SpringMassSolver | None = None, acc: bool = True) -> SequenceEval:
    """Roll out ``frames`` frames (default all) and score them (``acc=False`` leaves out the
    acceleration term); a divergence gives infinite loss."""
    n = data.num_frames - 1 if frames is None else frames
    lossv = np.full(n + 1, np.nan)
    err = np.full(n + 1, np.nan)
    try:
        xs, vs = rollout(model, data.controls, n, solver, data.tool_path())
    except SimulationDiverged:
        return SequenceEval(lossv, err, math.inf, math.inf, math.inf, diverged=True)
    train = [k for k in data.train_frames if k <= n]
    terms = dict.fromkeys(("chamfer", "track", "acc"), 0.0)
    for k in range(1, n + 1):
        pv = vs[k - 1]
        pa = vs[k - 1] - vs[k - 2] if k >= 2 and acc else None
        t = loss.frame(k, xs[k], vs[k], pv, pa)
        lossv[k] = t["total"]
        err[k] = loss.track_error(k, xs[k])
        if k in train:
            for name in terms:
                terms[name] += t[name] / len(train)
    val = [k for k in data.val_frames if k <= n]

    def mean(a, ks):
        vals = a[ks] if ks else np.array([])
        vals = vals[np.isfinite(vals)]
        return float(vals.mean()) if vals.size else float("nan")

    return SequenceEval(lossv, err, mean(lossv, train), mean(err, train), mean(err, val), terms=terms)


def frames_error(ev: SequenceEval, frames: range) -> float:
    """Mean tracking error (m) of ``ev`` over ``frames`` (NaN when none is finite; inf if diverged)."""
    if ev.diverged:
        return math.inf
    vals = ev.track_error[[k for k in frames if k < ev.track_error.size]]
    vals = vals[np.isfinite(vals)]
    return float(vals.mean()) if vals.size else float("nan")


def selection_count(data: SysIdData, share: float) -> int:
    """How many of the last training frames :func:`identify` holds out from fitting to choose between
    stages and epochs (the selection frames): ``share`` of the training frames, at least 1 when there are
    at least 4 training frames and ``share`` > 0, else 0 (the last stage run is then kept)."""
    n = len(data.train_frames)
    if share <= 0 or n < 4:
        return 0
    return int(min(max(round(share * n), 1), n - 3))


def fit_view(data: SysIdData, select: int) -> SysIdData:
    """``data`` with its last ``select`` training frames moved out of the training range (what the stages
    fit); the validation frames are unchanged in the data itself."""
    return replace(data, validation_frames=data.validation_frames + select) if select else data


# ----------------------------------------------------------------------------------------------
# progress


def _progress(enabled: bool):
    from twinbench.progress import progress_bar

    return progress_bar(enabled, "{task.fields[info]}")


# ----------------------------------------------------------------------------------------------
# stage 1: CMA-ES over global parameters

PENALTY = 1e6  # loss of a candidate whose simulation diverged or whose model cannot be built


SCAN_POINTS = 9  # stage 1's stiffness scan (log-spaced over the spring_Y range) before CMA-ES
ATTACHMENT_NAMES = ("control_radius", "control_max_neighbors")
ATTACHMENT_COARSE = 12
"""members of each attachment family scored before the walk (:func:`attachment_families`)"""


def attachment_families(data: SysIdData,
                        ranges: dict[str, SearchRange]) -> tuple[tuple[tuple[dict, int], ...], ...]:
    """The control attachments within the search ranges, as two nested families ordered from the fewest
    held particles to the most, each member one (``control_radius``, ``control_max_neighbors``): by radius
    (a member for every radius in the range at which some control point holds one more particle, the
    count at its top) and by count (one to the top count, the radius at its top). Empty without control
    points.

    Which particles a control point holds (those within the radius, nearest first, at most the count)
    changes the motion in steps that CMA-ES does not cross, and only the right particles fit: on the
    held-out family's irregular lift, the truth's attachment (7 particles) with one uniform stiffness
    scores 8x lower than stage 1's best, one particle more 4x higher than the truth's. So the stages score
    each family at their current point (:func:`stage1_cma`): ``ATTACHMENT_COARSE`` members log-spaced
    along it, then the neighbouring members of the best one while the loss falls (stage 1 at its end, or
    on the second start before its CMA-ES; stage 3 before its CMA-ES)."""
    if not data.num_controls:
        return ()
    rr, nr = ranges["control_radius"], ranges["control_max_neighbors"]
    pts = np.asarray(data.particles, np.float64)
    ctl = np.asarray(data.controls[0], np.float64)
    top = int(nr.hi)
    k = min(top, len(pts))
    dist = np.round(cKDTree(pts).query(ctl, k=k)[0].reshape(len(ctl), k), TIE_DECIMALS)  # as the builder

    def family(settings) -> tuple[tuple[dict, int], ...]:
        seen: dict[tuple, dict] = {}
        for r, n in settings:
            held = tuple(np.minimum(np.sum(dist <= r * (1.0 + RADIUS_SLACK), axis=1), n).tolist())
            if sum(held) and held not in seen:
                seen[held] = {"control_radius": float(r), "control_max_neighbors": int(n)}
        return tuple((seen[h], sum(h)) for h in sorted(seen, key=lambda h: (sum(h), h)))

    grow = np.unique(dist[(dist >= rr.lo) & (dist <= rr.hi)])  # radii at which a set grows
    grow = grow[np.r_[True, grow[1:] > grow[:-1] * (1.0 + 10 * RADIUS_SLACK)]]  # within the slack: one
    radii = [rr.lo, *(0.5 * (grow[:-1] + grow[1:])), rr.hi]  # between them: no distance ties
    counts = range(max(int(math.ceil(nr.lo)), 1), top + 1)
    return tuple(f for f in (family((r, top) for r in radii), family((rr.hi, n) for n in counts)) if f)


def stage1_loss(data: SysIdData, params: GlobalParams, base: SimParams, loss: SequenceLoss,
                device: str = "cpu", hold: tuple[np.ndarray, float] | None = None) -> float:
    """Stage 1's score of ``params``: Chamfer + tracking over the training frames (:data:`PENALTY` when
    the simulation diverges or the model cannot be built); ``hold``: the stiffness pattern held (stage 3,
    see :func:`build_model`)."""
    try:
        model = build_model(data, params, base, device, hold=hold)
        ev = evaluate(model, data, loss, frames=data.train_frames.stop - 1, acc=False)
        return ev.train_loss if math.isfinite(ev.train_loss) else PENALTY
    except ValueError:  # e.g. a rule that gives no springs at all
        return PENALTY


# ----------------------------------------------------------------------------------------------
# many candidates at once: a CMA-ES generation's candidates are independent simulations of a few dozen
# frames each. Threads do not help (a frame is thousands of short kernel launches from Python, which the
# GIL serialises) and splitting one short rollout over two processes costs more to start than it saves
# (SPLIT_PAYBACK_FRAMES); a pool of processes, one candidate each, does.

_POOL_WORKER: dict = {}  # in a CandidatePool process: its data, loss and device


def _pool_start(data: SysIdData, weights: LossWeights, device: str) -> None:
    # Ctrl-C reaches the whole process group: the parent stops the search (and this pool); a process here
    # would print its own KeyboardInterrupt traceback from its queue
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.environ[CPU_THREADS_ENV] = "1"  # the pool is the parallelism: each rollout on one core
    quiet_warp()
    watch_parent()  # a parent killed by SIGKILL leaves no process waiting on its queue
    _POOL_WORKER.update(data=data, loss=SequenceLoss(data, weights), device=device)


def _pool_score(job: tuple) -> float:
    params, base, hold = job
    return stage1_loss(_POOL_WORKER["data"], params, base, _POOL_WORKER["loss"], _POOL_WORKER["device"], hold)


class CandidatePool:
    """Scores (`sysid.stage1_loss`) of candidates on ``data`` in ``workers`` spawned processes (CMAConfig's
    ``workers``): ``losses`` takes jobs (GlobalParams, SimParams, held stiffness or None) and returns their
    scores in order. Where the processes cannot run (one was killed, or a script without an
    ``if __name__ == "__main__":`` guard spawned them), that batch and the rest are scored in this process,
    with a warning, and the values are the same."""

    def __init__(self, data: SysIdData, weights: LossWeights, device: str, workers: int):
        if workers < 2:
            raise ValueError(f"a candidate pool needs at least 2 workers, got {workers}")
        self.data, self.weights, self.device, self.workers = data, weights, device, int(workers)
        self._pool: ProcessPoolExecutor | None = ProcessPoolExecutor(
            self.workers, mp_context=mp.get_context("spawn"), initializer=_pool_start,
            initargs=(data, weights, device))
        self._loss = None

    def losses(self, jobs: list[tuple]) -> list[float]:
        if self._pool is not None and len(jobs) > 1:
            try:
                return list(self._pool.map(_pool_score, jobs))
            except BrokenProcessPool as err:
                warnings.warn(f"sysid: the candidate processes stopped ({err or 'a process died'}); the "
                              "candidates are scored in this process from now on", stacklevel=2)
                self.close()
        if self._loss is None:
            self._loss = SequenceLoss(self.data, self.weights)
        return candidate_losses(self.data, self._loss, self.device, jobs)

    def close(self) -> None:
        """Stop the processes (a ``with`` block does it; a pool left open is stopped at exit)."""
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def __enter__(self) -> CandidatePool:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def candidate_losses(data: SysIdData, loss: SequenceLoss, device: str, jobs: list[tuple],
                     pool: CandidatePool | None = None) -> list[float]:
    """``stage1_loss`` of each job (GlobalParams, SimParams, held stiffness or None), in order: at once in
    ``pool`` (on ``data``) when given, else one after another here."""
    if pool is not None:
        return pool.losses(jobs)
    return [stage1_loss(data, p, base, loss, device, hold) for p, base, hold in jobs]


def cma_search(f: Callable[[list[list[float]]], list[float]], x0: list[float], cfg: CMAConfig, budget: int,
               best: float = math.inf, sigma0: float | None = None) -> None:
    """CMA-ES on ``f`` over [0, 1]^n from ``x0`` (``cfg``: step ``sigma0`` unless given, population, seed,
    patience): at most ``budget`` evaluations; stops after ``cfg.patience`` generations without a 1 %
    improvement on the best value (``best``: the best before the search). ``f`` scores a generation's
    points at once (a list of values, in order). The caller keeps the best."""
    import cma

    opts = {"bounds": [0.0, 1.0], "maxfevals": max(budget, 1), "seed": cfg.seed + 1, "verbose": -9,
            "verb_log": 0, "verb_disp": 0}
    if cfg.popsize:
        opts["popsize"] = cfg.popsize
    es = cma.CMAEvolutionStrategy(list(x0), cfg.sigma0 if sigma0 is None else sigma0, opts)
    used, stalled, last_best = 0, 0, best
    while not es.stop() and used < budget:
        xs = es.ask()[: budget - used]
        vals = list(f(xs))
        used += len(vals)
        best = min([best, *vals])
        if len(vals) < es.popsize:
            break
        es.tell(xs, vals)
        if best < 0.99 * last_best:
            stalled, last_best = 0, best
        else:
            stalled += 1
        if cfg.patience and stalled >= cfg.patience:
            break


class AllDiverged(ValueError):
    """Every candidate of a search diverged."""

    def __init__(self, stage: str):
        super().__init__(f"{stage}: every candidate diverged; lower the spring_Y range (cma.ranges) or raise "
                         "the substeps")


def stage1_cma(data: SysIdData, base: SimParams, initial: GlobalParams, cfg: CMAConfig,
               weights: LossWeights = LossWeights(), device: str = "cpu", progress: bool = False,
               log: Callable[[str], None] = print,
               base_of: Callable[[GlobalParams], SimParams] | None = None,
               walk: bool = False,
               candidates: tuple[GlobalParams, ...] = (),
               hold: tuple[np.ndarray, float] | None = None,
               stage: str = "stage 1",
               attachments: tuple[tuple[tuple[dict, int], ...], ...] = (),
               scan_stiffness: bool = True, then_cma: bool = True,
               pool: CandidatePool | None = None) -> tuple[GlobalParams, list[dict]]:
    """CMA-ES over the searched global parameters (normalised to [0, 1], stiffness in log space).

    When stiffness is searched, a scan of ``SCAN_POINTS`` log-spaced stiffness values (the other
    parameters at ``initial``) first picks the scale of the start, so the search does not depend on a
    hand-set stiffness (the scan runs from soft to stiff and stops once two successive values rise past its
    minimum: the stiff candidates, which need the most substeps, are skipped when the answer is already
    bracketed); with ``walk`` (``initial.spring_Y`` is a guess from the data) the scan instead steps from
    it by half a decade towards the lower loss until the loss rises (a bracket around the guess). The
    ``candidates`` (e.g. the hand-set values a guess replaced) are scored too, so a guess never leaves the
    search worse off than its own start (``scan_stiffness=False`` skips the scan). Where the control
    attachment is searched, each family of ``attachments`` (:func:`attachment_families`) is scored next at
    the best point so far: its log-spaced coarse members, then the neighbours of the best member while the
    loss falls; where the stiffness is searched too, each member also at the stiffness that holds the
    object as firmly (the control springs' total stiffness kept). CMA-ES then starts from the best of
    these (with the families scored, the attachment stays the chosen one and CMA-ES searches the rest;
    ``then_cma=False``: no CMA-ES) and stops after ``cfg.patience`` generations without a 1 %
    improvement, or at the budget. Each
    evaluation simulates the training frames (with ``base_of(candidate)`` when given: substeps stable for
    the candidate's stiffness) and scores Chamfer + tracking (the acceleration term regularises stage 2's
    per-spring fit; in a global search it only favours the most damped candidate). With ``hold`` (stage
    3) every candidate keeps that stiffness pattern (:func:`build_model`). With ``pool`` (on ``data``
    and ``weights``), the candidates that do not depend on each other's scores (a generation, the
    attachment families' coarse members, the given candidates) are scored at once in its processes, with
    the same values and history as one at a time. Returns the best parameters and the history (one row per
    evaluation: index, loss, best-so-far, the candidate's searched values)."""
    ranges = parse_ranges(cfg.ranges)
    allowed = applicable_parameters(data, base)
    names = tuple(cfg.search) or allowed
    bad = [n for n in names if n not in allowed]
    if bad:
        raise ValueError(f"cma.search: {bad} do not affect this simulation (applicable: {list(allowed)}; "
                         "explicit springs fix the spring rule, self-contact needs self_collision)")
    if cfg.budget < 1:
        raise ValueError(f"cma.budget must be >= 1, got {cfg.budget}")
    initial = within_ranges(initial, names, ranges)
    candidates = tuple(within_ranges(c, names, ranges) for c in candidates)
    loss = SequenceLoss(data, weights)
    history: list[dict] = []
    best = (math.inf, initial)

    def objectives(cands: list[GlobalParams]) -> list[float]:
        """The scores of ``cands`` (at once in ``pool``), recorded in their order."""
        nonlocal best
        jobs = [(p, base_of(p) if base_of else base, hold) for p in cands]
        values = candidate_losses(data, loss, device, jobs, pool)
        for params, value in zip(cands, values, strict=True):
            if value < best[0]:
                best = (value, params)
            history.append({"evaluation": len(history), "loss": value, "best": best[0],
                            "params": {n: float(getattr(params, n)) for n in names}})
        return values

    def objective(params: GlobalParams) -> float:
        return objectives([params])[0]

    with _progress(progress) as bar:
        task = bar.add_task(f"{stage} (CMA-ES)", total=cfg.budget, info="")
        objective(initial)
        bar.advance(task)
        if scan_stiffness and "spring_Y" in names and cfg.budget > 2 * SCAN_POINTS and walk:
            r = ranges["spring_Y"]
            here, f_here = initial.spring_Y, best[0]
            for factor in (10 ** -0.5, 10 ** 0.5):  # downhill from the guess, half a decade a step
                nxt = min(max(here * factor, r.lo), r.hi)
                f_nxt = objective(replace(initial, spring_Y=nxt)) if nxt != here else math.inf
                bar.update(task, advance=1, info=f"best {best[0]:.3e}")
                steps = 0
                while f_nxt < f_here and steps < SCAN_POINTS and r.lo < nxt < r.hi:
                    here, f_here, nxt = nxt, f_nxt, min(max(nxt * factor, r.lo), r.hi)
                    f_nxt = objective(replace(initial, spring_Y=nxt))
                    bar.update(task, advance=1, info=f"best {best[0]:.3e}")
                    steps += 1
                if steps or f_nxt < f_here:
                    break  # went downhill this way: the other side is uphill from here
        elif scan_stiffness and "spring_Y" in names and cfg.budget > 2 * SCAN_POINTS:
            scan: list[float] = []
            for u in np.linspace(0.0, 1.0, SCAN_POINTS):  # stiff candidates cost most: stop once bracketed
                scan.append(objective(replace(initial, spring_Y=ranges["spring_Y"].decode(u))))
                bar.update(task, advance=1, info=f"best {best[0]:.3e}")
                if len(scan) >= 3 and scan[-1] > scan[-2] > min(scan) and min(scan) < PENALTY:
                    break
        if candidates:
            objectives(list(candidates))
            bar.advance(task, len(candidates))
        here = best[1]
        attach = bool(attachments) and set(ATTACHMENT_NAMES) <= set(names)
        if attach:
            m = build_model(data, here, base_of(here) if base_of else base, device)
            held_here = max(m.num_springs - m.num_object_springs, 1)

        def score(settings: list[tuple[dict, int]]) -> list[float]:
            """``here`` with each attachment (setting, control springs); where the stiffness is searched,
            also at the stiffness that holds the object as firmly as ``here`` (its control springs' total
            stiffness). Candidates past the budget score inf."""
            tries = []
            for i, (setting, held) in enumerate(settings):
                tries.append((i, replace(here, **setting)))
                if "spring_Y" in names and held != held_here:
                    r = ranges["spring_Y"]
                    firm = min(max(here.spring_Y * held_here / held, r.lo), r.hi)
                    tries.append((i, replace(tries[-1][1], spring_Y=firm)))
            tries = tries[: max(cfg.budget - len(history), 0)]
            out = [math.inf] * len(settings)
            for (i, _), value in zip(tries, objectives([p for _, p in tries]) if tries else [], strict=True):
                out[i] = min(out[i], value)
            bar.advance(task, len(settings))
            return out

        for members in attachments if attach else ():
            coarse = np.unique(np.round(np.geomspace(1, len(members), ATTACHMENT_COARSE))).astype(int) - 1
            scores = dict(zip(coarse.tolist(), score([members[j] for j in coarse]), strict=True))
            j = min(scores, key=scores.__getitem__)
            for step in (-1, 1):  # downhill along the family from its best coarse member
                while 0 <= j + step < len(members):
                    if j + step not in scores:
                        scores[j + step] = score([members[j + step]])[0]
                    if scores[j + step] >= scores[j]:
                        break
                    j += step
        # with the attachment chosen among the families, CMA-ES searches the rest (its steps would leave
        # the chosen particles for a neighbouring set at once)
        free = tuple(n for n in names if not (attach and n in ATTACHMENT_NAMES)) if then_cma else ()
        anchor = best[1]

        def decode(u) -> GlobalParams:  # CMA-ES's coordinates: the free parameters, from the anchor
            return replace(anchor, **{n: ranges[n].decode(ui) for n, ui in zip(free, u, strict=True)})

        x0 = [ranges[n].encode(getattr(anchor, n)) for n in free]

        def steps(us) -> list[float]:
            values = objectives([decode(u) for u in us])
            bar.update(task, advance=len(us), info=f"best {best[0]:.3e}")
            return values

        if len(free) == 1:  # cma needs >= 2 dimensions: a 1-D search samples the normalised line instead
            steps([[u] for u in np.linspace(0.0, 1.0, max(cfg.budget - len(history), 1))])
        elif free:
            cma_search(steps, x0, cfg, cfg.budget - len(history), best[0])
    if best[0] >= PENALTY:
        raise AllDiverged(stage)
    log(f"{stage}: {len(history)} evaluations, best training loss {best[0]:.4e}")
    return best[1], history


def rule_topologies(particles: np.ndarray, radii: SearchRange, max_neighbors: int,
                    count: int) -> list[tuple[float, int]]:
    """The distinct spring sets of the radius rule (:func:`radius_springs` at ``max_neighbors``) over the
    radius range ``radii``: at most ``count`` of them, spread evenly over the log of their spring counts
    (all of them where there are no more). Each is given by a radius inside its interval, the widest
    interval near its count (on a lattice the set changes only where a neighbour shell joins; on an
    irregular cloud at every pair distance). Returns (radius, springs) pairs, fewest springs first; empty
    where no radius in the range joins two particles."""
    pts = np.asarray(particles, np.float64)
    n = len(pts)
    if n < 2 or count < 1:
        return []
    k = min(int(max_neighbors) + 1, n)
    dist, idx = cKDTree(pts).query(pts, k=k, distance_upper_bound=radii.hi * (1.0 + RADIUS_SLACK))
    dist, idx = np.asarray(dist).reshape(n, k), np.asarray(idx).reshape(n, k)
    own = np.arange(n)[:, None]
    keep = np.isfinite(dist) & (idx != own)
    keep &= np.cumsum(keep, axis=1) <= max_neighbors  # the nearest max_neighbors others
    i, j = np.broadcast_to(own, idx.shape)[keep], idx[keep]
    d = dist[keep]
    far = d > MIN_REST_LENGTH
    pairs = np.unique(np.stack([np.minimum(i, j), np.maximum(i, j)], 1)[far], axis=0, return_index=True)[1]
    # the radius at which each pair joins the set (the rule takes distances up to its radius and a slack)
    joins = np.sort(np.round(d[far][pairs], TIE_DECIMALS)) / (1.0 + RADIUS_SLACK)
    inside = np.unique(joins[(joins > radii.lo) & (joins < radii.hi)])
    edges = np.concatenate([[radii.lo], inside, [radii.hi]])
    mids = np.sqrt(edges[:-1] * edges[1:])  # one radius inside each interval of one set
    counts = np.searchsorted(joins, mids, side="right")
    width = np.log(edges[1:] / edges[:-1])
    ok = counts > 0
    mids, counts, width = mids[ok], counts[ok], width[ok]
    if len(mids) == 0:
        return []
    if len(mids) > count:  # the widest interval near each of `count` spring counts, log-spaced
        chosen = set()
        for target in np.geomspace(counts[0], counts[-1], count):
            near = np.abs(np.log(counts / target)) <= 0.5 * np.log(counts[-1] / counts[0]) / max(count - 1, 1)
            cand = np.flatnonzero(near) if near.any() else [int(np.argmin(np.abs(np.log(counts / target))))]
            chosen.add(int(max(cand, key=lambda c: width[c])))
        pick = sorted(chosen)
    else:
        pick = range(len(mids))
    return [(float(mids[c]), len(radius_springs(pts, float(mids[c]), max_neighbors))) for c in pick]


def stage1_topologies(data: SysIdData, base: SimParams, initial: GlobalParams, cfg: CMAConfig,
                      weights: LossWeights = LossWeights(), device: str = "cpu", progress: bool = False,
                      log: Callable[[str], None] = print,
                      base_of: Callable[[GlobalParams], SimParams] | None = None, walk: bool = False,
                      candidates: tuple[GlobalParams, ...] = (),
                      attachments: tuple[tuple[tuple[dict, int], ...], ...] = (),
                      pool: CandidatePool | None = None) -> tuple[GlobalParams, list[dict]]:
    """Stage 1 where the spring rule is searched (``CMAConfig.topologies``): ``initial`` and
    ``candidates`` as they are; then each of the rule's :func:`rule_topologies` (at ``initial``'s
    neighbour cap) from ``initial`` with its radius, by :func:`stage1_cma`'s stiffness scan and attachment
    families without CMA-ES; then CMA-ES on the ``cfg.finalists`` whose start scored best, over the other
    searched parameters with the rule held. Returns the best parameters over all of it and one history
    (each row with every searched value, the rule's included)."""
    ranges = parse_ranges(cfg.ranges)
    names = tuple(cfg.search) or applicable_parameters(data, base)
    rest = tuple(n for n in names if n not in RULE_NAMES)
    start = within_ranges(initial, names, ranges)
    cap = int(start.spring_max_neighbors)
    history: list[dict] = []

    def add(rows: list[dict], held: GlobalParams) -> None:
        """``rows`` of one search, numbered on, each with every searched value (``held``'s where the search
        held it: the rule, an attachment chosen before)."""
        for r in rows:
            best = min(r["loss"], history[-1]["best"]) if history else r["loss"]
            values = {n: float(getattr(held, n)) for n in names} | r["params"]
            history.append(r | {"evaluation": len(history), "best": best, "params": values})

    def quiet(_message: str) -> None:  # one line a searched set below instead
        pass

    best, rows = stage1_cma(data, base, start, replace(cfg, budget=1 + len(candidates)), weights, device,
                            False, quiet, base_of=base_of, candidates=candidates, scan_stiffness=False,
                            then_cma=False, pool=pool)
    add(rows, start)
    found = [(min(r["loss"] for r in rows), best)]
    tops = rule_topologies(data.particles, ranges["spring_radius"], cap, cfg.topologies)
    starts = []
    for radius, springs in tops:
        at = replace(start, spring_radius=radius)
        try:
            p, rows = stage1_cma(data, base, at, replace(cfg, search=rest),
                                 weights, device, progress, quiet, base_of=base_of, walk=walk,
                                 attachments=attachments, then_cma=False, pool=pool,
                                 stage=f"stage 1, radius {100 * radius:.2f} cm")
        except AllDiverged:  # every candidate of this set diverged
            continue
        add(rows, at)
        starts.append((min(r["loss"] for r in rows), radius, springs, p))
    starts.sort(key=lambda t: t[0])
    attached = bool(attachments) and set(ATTACHMENT_NAMES) <= set(rest)
    search = tuple(n for n in rest if not (attached and n in ATTACHMENT_NAMES))
    for f_start, radius, springs, p0 in starts[: cfg.finalists]:
        p, rows = stage1_cma(data, base, p0, replace(cfg, search=search), weights, device, progress, quiet,
                             base_of=base_of, scan_stiffness=False, pool=pool,
                             stage=f"stage 1, radius {100 * radius:.2f} cm")
        add(rows, p0)
        found.append((min(r["loss"] for r in rows), p))
        log(f"stage 1: spring radius {100 * radius:.2f} cm ({springs} springs): start {f_start:.4e}, "
            f"searched {found[-1][0]:.4e}")
    if not starts:
        raise AllDiverged("stage 1")
    loss, params = min(found, key=lambda t: t[0])
    log(f"stage 1: {len(history)} evaluations over {len(tops)} spring sets of the radius rule "
        f"({', '.join(f'{100 * r:.2f} cm: {c}' for r, c in tops)} springs), the best "
        f"{min(cfg.finalists, len(starts))} searched; best training loss {loss:.4e} at radius "
        f"{100 * params.spring_radius:.2f} cm")
    return params, history


STAGE4_SPAN = 3.0
"""stage 4 moves each stiffness region within this factor of stage 2's (or 3's) value"""
STAGE4_SIGMA = 0.15
"""stage 4's initial CMA-ES step (normalised units): a refinement around the fitted point"""


def stage4_cma(data: SysIdData, params: GlobalParams, hold: tuple[np.ndarray, float], region: np.ndarray,
               names: tuple[str, ...], cfg: CMAConfig, budget: int,
               base_of: Callable[[GlobalParams, float], SimParams], weights: LossWeights = LossWeights(),
               device: str = "cpu", *, hold_scale: bool = False, y_bounds: tuple[float, float] = (1.0, 1e5),
               progress: bool = False, log: Callable[[str], None] = print,
               pool: CandidatePool | None = None,
               ) -> tuple[GlobalParams, tuple[np.ndarray, float], list[dict]]:
    """Stage 4: CMA-ES (``STAGE4_SIGMA``, ``budget`` evaluations) over the object springs' log Y per
    ``region`` (one index per object spring; each region shifted by at most a factor ``STAGE4_SPAN``, kept
    in ``y_bounds``), the control springs' log Y (with control points) and the global parameters ``names``,
    from ``params`` and ``hold`` (object springs' log Y, control springs' log Y); ``hold_scale`` keeps the
    object springs' mean log Y (the measured stiffness that was kept). Scored as stage 1 (Chamfer +
    tracking over the training frames) with ``base_of(candidate, stiffest Y)``, a generation at once in
    ``pool`` when given. Returns the best parameters, stiffness and the history."""
    ranges = parse_ranges(cfg.ranges)
    obj_y, ctl_y = np.asarray(hold[0], np.float64), float(hold[1])
    _, inv = np.unique(region, return_inverse=True)
    counts = np.bincount(inv).astype(np.float64)
    n_y = len(counts) + (1 if data.num_controls else 0)
    span = math.log(STAGE4_SPAN)
    lo, hi = math.log(y_bounds[0]), math.log(y_bounds[1])
    loss = SequenceLoss(data, weights)
    history: list[dict] = []
    best: list = [math.inf, params, (obj_y, ctl_y)]

    def decode(u) -> tuple[GlobalParams, tuple[np.ndarray, float]]:
        shift = (np.clip(np.asarray(u[:n_y], np.float64), 0.0, 1.0) - 0.5) * 2.0 * span
        obj = shift[: len(counts)]
        if hold_scale:
            obj = obj - np.average(obj, weights=counts)
        y = (np.clip(obj_y + obj[inv], lo, hi), float(np.clip(ctl_y + shift[-1], lo, hi)) if data.num_controls
             else ctl_y)
        return replace(params, **{n: ranges[n].decode(x) for n, x in zip(names, u[n_y:], strict=True)}), y

    with _progress(progress) as bar:
        task = bar.add_task("stage 4 (CMA-ES)", total=budget, info="")

        def objectives(us) -> list[float]:
            cands = [decode(u) for u in us]
            jobs = [(p, base_of(p, float(np.exp(max(y[0].max(), y[1])))), y) for p, y in cands]
            values = candidate_losses(data, loss, device, jobs, pool)
            for (p, y), value in zip(cands, values, strict=True):
                if value < best[0]:
                    best[:] = [value, p, y]
                history.append({"evaluation": len(history), "loss": value, "best": best[0],
                                "params": {n: float(getattr(p, n)) for n in names}})
            bar.update(task, advance=len(us), info=f"best {best[0]:.3e}")
            return values

        x0 = [0.5] * n_y + [ranges[n].encode(getattr(params, n)) for n in names]
        objectives([x0])
        if len(x0) > 1:  # cma needs >= 2 dimensions
            cma_search(objectives, x0, replace(cfg, patience=0), budget - 1, best[0], sigma0=STAGE4_SIGMA)
    log(f"stage 4: {len(history)} evaluations, best training loss {best[0]:.4e}")
    return best[1], best[2], history


# ----------------------------------------------------------------------------------------------
# stage 2: Adam on per-spring log Y, truncated backpropagation over one frame


class Adam:
    """Adam on a float64 vector with projection onto [lo, hi] after each step."""

    def __init__(self, x: np.ndarray, lr: float, betas=(0.9, 0.99), eps: float = 1e-12,
                 lo: float = -math.inf, hi: float = math.inf):
        self.x = np.asarray(x, np.float64).copy()
        self.lr, self.b1, self.b2, self.eps, self.lo, self.hi = lr, betas[0], betas[1], eps, lo, hi
        self.m = np.zeros_like(self.x)
        self.v = np.zeros_like(self.x)
        self.t = 0

    def step(self, g: np.ndarray) -> np.ndarray:
        self.t += 1
        self.m = self.b1 * self.m + (1 - self.b1) * g
        self.v = self.b2 * self.v + (1 - self.b2) * g * g
        mh = self.m / (1 - self.b1 ** self.t)
        vh = self.v / (1 - self.b2 ** self.t)
        self.x = np.clip(self.x - self.lr * mh / (np.sqrt(vh) + self.eps), self.lo, self.hi)
        return self.x


CONTACT_NAMES = ("ground_restitution", "ground_friction", "object_restitution", "object_friction")
CONTACT_MAX = np.array([1.0, 2.0, 1.0, 2.0])  # the kernels clamp restitution to [0, 1], friction to [0, 2]


def fitted_contacts(model: SpringMassModel) -> list[int]:
    """Indices (into CONTACT_NAMES) of the contact parameters that act on this model: the ground's with
    the ground on, the object-object ones with particle collisions (self-collision or several bodies)."""
    return ([0, 1] if model.params.ground else []) + ([2, 3] if model.particle_collisions else [])


def frame_gradient(model: SpringMassModel, solver: SpringMassSolver, state, control, loss: SequenceLoss,
                   k: int, prev_v=None, prev_acc=None):
    """Simulate frame ``k`` from ``state`` under ``wp.Tape`` and backpropagate the frame loss.

    Returns (loss terms, d loss / d log_y (per spring, float64), final x, final v, d loss / d contact
    coefficients (4, float64: CONTACT_NAMES order)). The loss gradient w.r.t. the final positions and
    velocities is the adjoint injected into the tape.
    """
    tape = wp.Tape()
    with tape:
        states = solver.simulate_frame_tape(state, control)
    last = states[-1]
    bad = check_divergence(last, solver.max_speed)
    if bad.size:
        tape.reset()
        raise SimulationDiverged(bad, f" in frame {k} of stage 2")
    x, v = last.numpy()
    terms, gx, gv = loss.frame(k, x, v, prev_v, prev_acc, grad=True)
    dev = model.device
    model.log_y.grad.zero_()
    model.contact_coeffs.grad.zero_()
    tape.backward(grads={last.x: wp.array(gx.astype(np.float32), dtype=wp.vec3, device=dev),
                         last.v: wp.array(gv.astype(np.float32), dtype=wp.vec3, device=dev)})
    g = model.log_y.grad.numpy().astype(np.float64)
    gc = model.contact_coeffs.grad.numpy().astype(np.float64)
    tape.zero()
    tape.reset()
    return terms, g, x, v, gc


def spring_regions(model: SpringMassModel, regions: int, seed: int = 0) -> np.ndarray:
    """Region index per spring: the object springs clustered into ``regions`` spatial regions (k-means of
    their rest midpoints), the control springs one more region; ``regions`` 0 (or at least the number of
    object springs) gives every spring its own value."""
    from scipy.cluster.vq import kmeans2

    n_obj, n_all = model.num_object_springs, model.num_springs
    if regions <= 0 or regions >= n_obj:
        return np.arange(n_all)
    sp = model.springs_np[:n_obj]
    mid = 0.5 * (model.x0_np[sp[:, 0]] + model.x0_np[sp[:, 1]]).astype(np.float64)
    _, label = kmeans2(mid, regions, seed=seed, minit="++")
    _, label = np.unique(label, return_inverse=True)  # drop empty clusters
    return np.concatenate([label, np.full(n_all - n_obj, label.max() + 1)]).astype(np.int64)


MAX_REGIONS = 64  # region_information costs one rollout per region

REGION_STD = math.log(1.5)
"""a region's stiffness counts as constrained by the motion when its standard deviation (log Y, from the
Fisher information of the tracks, :func:`region_information`) is below this: known within a factor 1.5"""


def _track_vector(xs: np.ndarray, data: SysIdData, frames) -> np.ndarray:
    """Simulated minus observed positions of the motion-valid tracked points over ``frames``, flattened."""
    parts = [xs[k][data.tracked_indices[data.motion_valid[k]]] - data.tracked[k][data.motion_valid[k]]
             for k in frames]
    return np.concatenate([p.ravel() for p in parts]) if parts else np.zeros(0)


def _track_ids(data: SysIdData, frames) -> np.ndarray:
    """Which track each entry of :func:`_track_vector` belongs to (its index in ``data.tracked``)."""
    parts = [np.repeat(np.flatnonzero(data.motion_valid[k]), 3) for k in frames]
    return np.concatenate(parts) if parts else np.zeros(0, np.int64)


def _region_jacobian(model: SpringMassModel, data: SysIdData, region: np.ndarray, frames: list[int],
                     delta: float, solver: SpringMassSolver) -> tuple[np.ndarray, np.ndarray]:
    """(J, r0): the tracking residual ``r0`` (simulated minus observed, :func:`_track_vector`) of a
    whole-sequence rollout of ``model`` and its Jacobian w.r.t. each region's log Y by backward finite
    differences (every spring of the region ``delta`` softer: stable wherever the model is); a column
    whose rollout diverged is NaN. ``model``'s stiffness is left as it was."""
    log_y0 = model.log_y_np.copy()
    last = max(frames)
    tool = data.tool_path()
    r0 = _track_vector(rollout(model, data.controls, last, solver, tool)[0].astype(np.float64), data, frames)
    jac = np.zeros((r0.size, int(region.max()) + 1))
    try:
        for r in range(jac.shape[1]):
            model.set_spring_log_y(log_y0 - delta * (region == r))
            try:
                xs = rollout(model, data.controls, last, solver, tool)[0].astype(np.float64)
                jac[:, r] = (r0 - _track_vector(xs, data, frames)) / delta
            except SimulationDiverged:
                jac[:, r] = np.nan
    finally:
        model.set_spring_log_y(log_y0)
    return jac, r0


def _fitted_frames(data: SysIdData) -> list[int]:
    return [k for k in data.train_frames if k >= 1]


def region_information(model: SpringMassModel, data: SysIdData, region: np.ndarray, *, delta: float = 0.1,
                       std_limit: float = REGION_STD) -> dict:
    """How well the fitted frames of ``data`` constrain each stiffness region of ``model`` (``region``: per
    spring, as :func:`spring_regions`), measured on whole-sequence rollouts (not one-frame gradients).

    The Jacobian ``J`` of the tracked positions (motion-valid, fitted frames) w.r.t. each region's log Y
    is taken by finite differences (:func:`_region_jacobian`); with the fit's own tracking residual as
    the noise (``sigma``, per coordinate), the Fisher information is ``J^T J / sigma^2`` and each region's
    standard deviation (log Y) is the square root of the diagonal of its pseudo-inverse, so a region that
    trades off against a neighbour is as uncertain as the pair. That holds for independent noise; where
    the model cannot follow the motion (a coarser object than the real one), each track's residual is
    one error drawn out over the frames, so the standard deviation is also taken cluster-robust with the
    tracks as clusters (:func:`_region_std`) and the larger of the two is reported. Returns per region
    (the last one holds the control springs when the model has them): ``std``, ``std_white`` (the
    independent-noise figure), ``constrained`` (``std < std_limit``), ``springs``; plus ``sigma`` (m).
    ``model``'s stiffness is left as it was. Raises SimulationDiverged if the base rollout diverges."""
    frames = _fitted_frames(data)
    jac, r0 = _region_jacobian(model, data, region, frames, delta, SpringMassSolver(model))
    sigma2 = max(float(np.mean(r0 * r0)) if r0.size else 0.0, 1e-12)
    n_reg = jac.shape[1]
    white = _region_std(jac, sigma2)
    std = np.maximum(white, _region_std(jac, sigma2, r0, _track_ids(data, frames)))
    counts = np.bincount(region, minlength=n_reg)
    return {"sigma": math.sqrt(sigma2), "std_limit": std_limit,
            "regions": [{"springs": int(counts[r]), "std": float(std[r]), "std_white": float(white[r]),
                         "constrained": bool(std[r] < std_limit)} for r in range(n_reg)]}


def by_region(model: SpringMassModel, region: np.ndarray) -> bool:
    """Whether ``region`` groups springs into few enough regions for :func:`region_information` (one
    rollout per region: at most ``MAX_REGIONS``, and not one region per spring)."""
    n_reg = int(region.max()) + 1
    return n_reg <= MAX_REGIONS and n_reg < model.num_springs


def _region_std(jac: np.ndarray, sigma2: float, residual: np.ndarray | None = None,
                clusters: np.ndarray | None = None) -> np.ndarray:
    """Per column of ``jac``: the standard deviation of its parameter from the Fisher information
    ``J^T J / sigma2`` (square root of the pseudo-inverse's diagonal; inf for a column that moves
    nothing or whose rollout diverged). With ``residual`` and ``clusters`` (a label per row) instead the
    cluster-robust ("sandwich") figure, ``B M B`` with ``B = (J^T J)^+`` and ``M`` the sum over clusters
    of ``g g^T``, ``g = J_c^T r_c``: right when the rows of a cluster share their errors (a track's
    model error over the frames), where the Fisher figure is too narrow by up to the square root of the
    rows per cluster."""
    std = np.full(jac.shape[1], np.inf)
    ok = np.all(np.isfinite(jac), axis=0)
    if ok.any():
        j = jac[:, ok]
        fisher = j.T @ j / max(sigma2, 1e-12)
        cov = np.linalg.pinv(fisher, rcond=1e-10, hermitian=True)
        if residual is not None and clusters is not None:
            _, label = np.unique(clusters, return_inverse=True)
            g = np.zeros((int(label.max()) + 1 if label.size else 0, j.shape[1]))
            np.add.at(g, label, j * residual[:, None])
            bread = cov / max(sigma2, 1e-12)  # (J^T J)^+
            cov = bread @ (g.T @ g) @ bread
        std[ok] = np.where(np.diag(fisher) > 0, np.sqrt(np.maximum(np.diag(cov), 0.0)), np.inf)
    return std


def stage2_adam(model: SpringMassModel, data: SysIdData, cfg: AdamConfig,
                weights: LossWeights = LossWeights(), progress: bool = False,
                log: Callable[[str], None] = print, select: int = 0,
                hold_scale: bool = False) -> tuple[np.ndarray, list[dict]]:
    """Adam on ``model.log_y`` (finalized with ``requires_grad=True``) and, with ``cfg.fit_contact``, on
    the contact coefficients that act (``fitted_contacts``, in logit space), one step per fitted frame.
    With ``hold_scale`` the object springs' mean log Y (weighted by springs per region) stays at its start
    after every step: only the stiffness pattern is fitted, not its overall scale (for a scale that stage 1
    found the motion does not constrain).

    The last ``select`` training frames are not fitted: they are the selection frames (see
    :func:`selection_count`). After each epoch the whole sequence is rolled out (fast path) and the
    parameters with the lowest fitted loss are kept (with ``cfg.epoch_by_selection``, the lowest tracking
    error on the selection frames; the validation frames only report). Stops early, keeping the best
    parameters, when a taped frame diverges. Returns (best log_y, history rows per epoch); the best
    contact coefficients are left in ``model.contact_coeffs``."""
    if not model.requires_grad:
        raise ValueError("stage2_adam needs a model finalized with requires_grad=True")
    if cfg.epochs < 0 or not (0 < cfg.y_min < cfg.y_max):
        raise ValueError(f"adam: need epochs >= 0 and 0 < y_min < y_max, got {cfg}")
    sel = range(data.train_frames.stop - select, data.train_frames.stop)
    full, data = data, fit_view(data, select)
    loss = SequenceLoss(data, weights)
    solver = SpringMassSolver(model)
    eval_solver = SpringMassSolver(model)
    ctl, tool = model.control(), data.tool_path()
    lo, hi = math.log(cfg.y_min), math.log(cfg.y_max)
    region = spring_regions(model, cfg.regions)
    n_reg = int(region.max()) + 1
    start = np.bincount(region, np.clip(model.log_y_np.astype(np.float64), lo, hi), n_reg) \
        / np.maximum(np.bincount(region, minlength=n_reg), 1)
    opt = Adam(start, cfg.lr, cfg.betas, cfg.eps, lo, hi)
    model.set_spring_log_y(opt.x[region])
    n_obj = model.num_object_springs
    obj_w = np.bincount(region[:n_obj], minlength=n_reg).astype(np.float64)  # 0 for the control region
    obj_mean = float(obj_w @ start / obj_w.sum())

    def step(g: np.ndarray) -> np.ndarray:
        x = opt.step(g)
        if hold_scale:  # back to the start's mean, the shift shared by the object regions, within bounds
            x[obj_w > 0] = np.clip(x[obj_w > 0] - (obj_w @ x / obj_w.sum() - obj_mean), lo, hi)
        return x
    fit = fitted_contacts(model) if cfg.fit_contact else []
    coeffs = model.contact_coeffs.numpy().astype(np.float64)
    frac = np.clip(coeffs[fit] / CONTACT_MAX[fit], 1e-4, 1.0 - 1e-4)
    opt_c = Adam(np.log(frac / (1.0 - frac)), cfg.contact_lr, cfg.betas, 1e-8)

    def set_contacts(u: np.ndarray) -> None:
        coeffs[fit] = CONTACT_MAX[fit] / (1.0 + np.exp(-u))
        model.set_contact_coeffs(coeffs)

    if fit:
        set_contacts(opt_c.x)

    by_sel = select and cfg.epoch_by_selection

    def score(ev: SequenceEval) -> float:  # what chooses the epoch: never the validation frames
        return frames_error(ev, sel) if by_sel else ev.train_loss

    ev = evaluate(model, data, loss, solver=eval_solver)
    best = (score(ev), opt.x[region], opt_c.x.copy())
    best_fit = ev.train_loss

    def row(epoch: int, taped: float, ev, per_iter: float) -> dict:
        out = {"epoch": epoch, "taped_loss": taped, "train_loss": ev.train_loss,
               "train_error": ev.train_error, "select_error": frames_error(ev, sel),
               "val_error": frames_error(ev, full.val_frames), "seconds_per_iteration": per_iter}
        return out | {CONTACT_NAMES[i]: float(coeffs[i]) for i in fit}

    history = [row(0, float("nan"), ev, float("nan"))]
    train = list(data.train_frames)
    contact_from = cfg.contact_after * cfg.epochs  # contact joins after this epoch, or at a stall
    stalled, ref = 0, best_fit
    with _progress(progress) as bar:
        task = bar.add_task("stage 2 (Adam)", total=cfg.epochs * len(train), info="")
        for epoch in range(1, cfg.epochs + 1):
            if fit and epoch - 1 <= contact_from < epoch:
                stalled = 0  # the contact's first epoch: it gets its own patience
            state = model.state()
            prev_v, prev_acc = model.v0_np.astype(np.float64), None
            total, t0 = 0.0, time.perf_counter()
            try:
                for k in train:
                    set_frame_inputs(model, ctl, data.controls, tool, k)
                    terms, g, x, v, gc = frame_gradient(model, solver, state, ctl, loss, k, prev_v, prev_acc)
                    total += terms["total"]
                    model.set_spring_log_y(step(np.bincount(region, g, n_reg))[region])
                    if fit and epoch > contact_from:  # chain rule: c = max sigmoid(u)
                        sig = coeffs[fit] / CONTACT_MAX[fit]
                        set_contacts(opt_c.step(gc[fit] * CONTACT_MAX[fit] * sig * (1.0 - sig)))
                    state = model.state()
                    state.x.assign(x)
                    state.v.assign(v)
                    v = v.astype(np.float64)
                    prev_acc, prev_v = v - prev_v, v
                    bar.update(task, advance=1, info=f"epoch {epoch} loss {terms['total']:.3e}")
            except SimulationDiverged as exc:
                log(f"stage 2: stopped at epoch {epoch}, {exc}; keeping the best parameters so far "
                    "(lower adam.y_max or raise the substeps)")
                history.append({"epoch": epoch, "diverged": True})
                break
            per_iter = (time.perf_counter() - t0) / len(train)
            ev = evaluate(model, data, loss, solver=eval_solver)
            if score(ev) < best[0]:
                best = (score(ev), opt.x[region], opt_c.x.copy())
            best_fit = min(best_fit, ev.train_loss)
            history.append(row(epoch, total / len(train), ev, per_iter))
            stalled, ref = (0, best_fit) if best_fit < 0.995 * ref else (stalled + 1, ref)
            if cfg.patience and stalled >= cfg.patience:
                if fit and epoch <= contact_from:  # stiffness alone has stalled: the contact joins now
                    contact_from, stalled = epoch, 0
                else:
                    log(f"stage 2: stopped after epoch {epoch}: {stalled} epochs without a 0.5 % improvement")
                    break
    model.set_spring_log_y(best[1])
    if fit:
        set_contacts(best[2])
    what = f"best selection-frame error {1e3 * best[0]:.3f} mm" if by_sel else \
        f"best training loss {best[0]:.4e} (its acceleration term included, which stages 1 and 3 leave out)"
    log(f"stage 2: {len(history) - 1} epochs, {what}")
    return best[1].astype(np.float32), history


# ----------------------------------------------------------------------------------------------
# the whole identification


@dataclass
class SysIdResult:
    """What :func:`identify` found: final global parameters, per-spring log Y (object springs first,
    then control springs), the model, evaluations ('initial', 'stage1', 'stage2', 'stage3', 'stage4' as
    run, and 'final') and histories."""

    params: GlobalParams
    sim: SimParams
    log_y: np.ndarray
    model: SpringMassModel
    evals: dict[str, SequenceEval]
    stage1_history: list[dict] = field(default_factory=list)
    stage2_history: list[dict] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    config: FitConfig | None = None
    notes: list[str] = field(default_factory=list)
    """what the user must know: a stage that did not improve on its start, a bound that was hit"""
    identifiability: dict[str, dict] = field(default_factory=dict)
    """per searched global parameter: the interval of the candidates within 50 % of the best loss and
    whether the motion constrains it (see :func:`identifiability`), from the last search of it (stage 3
    for what it searched, else stage 1)"""
    regions: np.ndarray | None = None
    """stage 2's stiffness region per spring (``spring_regions``: object springs, then control springs in
    one more region); every spring its own region when fitted per spring; None when neither stage 2's
    nor stage 3's result (stage 2's stiffness) is the one kept"""
    guesses: dict[str, dict] = field(default_factory=dict)
    """the physically scaled guesses stage 1 started from (``physics.sysid_guess``): per parameter its
    value (None where the motion does not show it), how it was measured, and whether it was used"""
    selection: dict = field(default_factory=dict)
    """which stage was kept and why: the selection frames (the last training frames, held out from
    fitting), each stage's tracking error on them, the kept stage, the rule"""
    region_identifiability: dict = field(default_factory=dict)
    """per stiffness region of the kept stage 2 (``regions``' order): whether the fitted motion constrains
    its stiffness (:func:`region_information`: standard deviation of log Y from the tracks' Fisher
    information); empty when neither stage 2 nor stage 3 is kept, or when fitted per spring"""
    stage3_history: list[dict] = field(default_factory=list)
    """stage 3's evaluations (as ``stage1_history``: the global parameters other than the spring rule
    searched again with stage 2's stiffness held)"""
    inputs: dict = field(default_factory=dict)
    """what was done to the measured input before simulating it: per kinematic input (controls,
    tool_translation, tool_rotation) its estimated noise, whether it was smoothed and by how much it moved
    (``sysid_guess.smoothed_inputs``); "particles_below_ground" with the ground on
    (``sysid_guess.grounded``)"""
    stage4_history: list[dict] = field(default_factory=list)
    """stage 4's evaluations (as ``stage1_history``: its global parameters; the region values are not
    listed)"""

    @property
    def object_spring_Y(self) -> np.ndarray:
        """Effective per-spring stiffness of the object springs (clamped as the solver does)."""
        n = self.model.num_object_springs
        y = np.exp(self.log_y[:n].astype(np.float64))
        return np.clip(y, self.sim.spring_Y_min, self.sim.spring_Y_max)


MIN_NEAR = 5
"""near-best stage-1 candidates needed before :func:`identifiability` calls a parameter constrained or not"""


def identifiability(history: list[dict], ranges: dict[str, SearchRange] | None = None,
                    tol: float = 0.5, constrained_width: float = 0.3) -> dict[str, dict]:
    """Which global parameters stage 1's motion constrains: for each searched parameter, the interval
    of the candidates whose loss is within ``tol`` (relative) of the best, and its width as a fraction
    of the search range (normalised, log scale for stiffness); ``constrained`` when the width is below
    ``constrained_width`` and at least :data:`MIN_NEAR` candidates fall within the tolerance (else too few
    to say)."""
    ranges = ranges or DEFAULT_RANGES
    rows = [r for r in history if "params" in r and math.isfinite(r["loss"]) and r["loss"] < PENALTY]
    if not rows:
        return {}
    best = min(r["loss"] for r in rows)
    near = [r for r in rows if r["loss"] <= best * (1.0 + tol)]
    out = {}
    for name in rows[0]["params"]:
        vals = [r["params"][name] for r in near]
        rng = ranges[name]
        width = rng.encode(max(vals)) - rng.encode(min(vals))
        out[name] = {"best": min(rows, key=lambda r: r["loss"])["params"][name], "low": min(vals),
                     "high": max(vals), "width": width, "samples": len(vals),
                     "constrained": bool(width < constrained_width and len(vals) >= MIN_NEAR)}
    return out


def keep_unconstrained_guesses(params: GlobalParams, start: GlobalParams, guesses: dict[str, dict],
                               ident: dict[str, dict], history: list[dict], tol: float,
                               score: Callable[[GlobalParams], float], notes: list[str]) -> GlobalParams:
    """``params`` with each parameter that the motion does not constrain (``ident``) set back to the value
    measured for it in the data (``guesses`` that stage 1 started from, ``start``'s value: point
    estimates, not lower bounds), when the parameters so changed score within ``tol`` (relative) of stage
    1's best training loss: in a flat valley the search's best point is as arbitrary as any other, the
    measured value is not. The trial is appended to ``history`` (``guess_kept``), the outcome to
    ``notes``."""
    names = [n for n, g in guesses.items()
             if g.get("used") and not g.get("lower_bound") and n in ident and not ident[n]["constrained"]
             and ident[n]["samples"] >= MIN_NEAR  # else too few near-best candidates to say
             and not math.isclose(getattr(params, n), getattr(start, n), rel_tol=1e-3)]
    if not names:
        return params
    trial = replace(params, **{n: getattr(start, n) for n in names})
    best = min(r["loss"] for r in history)
    value = score(trial)
    kept = value <= best * (1.0 + tol)
    history.append({"evaluation": len(history), "loss": value, "best": min(best, value),
                    "params": {n: float(getattr(trial, n)) for n in history[0]["params"]},
                    "guess_kept": kept})
    what = ", ".join(f"{n} {getattr(params, n):.4g} -> {getattr(trial, n):.4g} (near-best candidates "
                     f"{ident[n]['low']:.4g}-{ident[n]['high']:.4g})" for n in names)
    change = f"{100 * (value / best - 1):+.1f} %" if value < PENALTY else "diverged"
    if kept:
        notes.append(f"the motion does not constrain {', '.join(names)}: the values measured in it are kept "
                     f"instead of stage 1's arbitrary point in the flat valley: {what}; training loss "
                     f"{change} (within {tol:.0%})")
        for n in names:
            ident[n]["guess_kept"] = True
        return trial
    notes.append(f"the motion does not constrain {', '.join(names)}, but the values measured in it score "
                 f"{change} against stage 1's best (over {tol:.0%}): stage 1's values are kept ({what})")
    return params


def balanced_weights(weights: LossWeights, terms: dict[str, float], share: float,
                     log: Callable[[str], None] = print) -> LossWeights:
    """``weights`` with the acceleration weight lowered so that, at the measured ``terms`` (training
    means), the acceleration term is at most ``share`` of the Chamfer + tracking terms (unchanged when
    it already is, or when ``share`` is 0 or a term is missing)."""
    data_terms = terms.get("chamfer", 0.0) + terms.get("track", 0.0)
    acc = terms.get("acc", 0.0)
    if not (share > 0 and weights.acc > 0 and acc > share * data_terms > 0):
        return weights
    new = replace(weights, acc=weights.acc * share * data_terms / acc)
    log(f"stage 2: acceleration weight {weights.acc:g} -> {new.acc:.3g} (its term was "
        f"{acc / data_terms:.2f}x the Chamfer + tracking terms; adam.acc_share {share:g})")
    return new


def identify(data: SysIdData, cfg: FitConfig, *, base: SimParams | None = None,
             log: Callable[[str], None] = print) -> SysIdResult:
    """Run the configured stages on ``data``; ``base`` overrides the SimParams built from ``cfg``.

    Stage 1: CMA-ES over the global parameters (one stiffness for every spring), from the guesses measured
    in the motion. Stage 2: Adam on per-region (or per-spring) stiffness and the contact values. Stage 3:
    CMA-ES again over the global parameters other than the spring rule, with stage 2's stiffness held
    (stage 1 chose them under a uniform stiffness they partly stood in for), after scoring the control
    attachments (:func:`attachment_families`) at stage 2's point. Stages 2 and 3 run ``cfg.rounds`` times,
    each round from the last one's stiffness pattern and global values. With ``cfg.stage4``, stage 4 then
    searches the stiffness regions and the contact and damping values together (:func:`stage4_cma`).
    With control points, stage 1's end point also has its attachment scored among the families before
    stage 2. With
    ``cfg.attachment_starts`` and control points, when the result's training tracking error is over
    ``cfg.second_start_over_floor`` times the tracks' noise floor, the stages run a second time with
    stage 1 scoring the families before its CMA-ES, and the run with the lower training tracking error is
    kept (``SysIdResult.selection["starts"]``).

    With automatic substeps (``cfg.dt == cfg.substeps == 0``, the default), every simulation runs at the
    fewest substeps stable for its stiffness and dashpot (``stable_substeps``): stage 1's candidates
    cannot diverge, and stage 2 runs stably at its upper stiffness bound.

    The stages fit the training frames less the last ``cfg.select_frames`` share of them (the selection
    frames, :func:`selection_count`); of the stages run (the initial values included), the one with the
    lowest tracking error on the selection frames is kept, the later one on a tie. The validation frames
    neither fit nor choose; a kept stage whose validation error is worse than the stage before it is
    named in the notes."""
    from .sysid_guess import grounded, physical_guesses, smoothed_inputs, track_noise

    cfg.check()
    pairs = data.springs if data.springs is not None else \
        radius_springs(data.particles, cfg.initial.spring_radius, int(cfg.initial.spring_max_neighbors))
    if len(pairs) == 0:
        raise ValueError(f"{data.source}: the object has no springs: no two of its {len(data.particles)} "
                         f"particles lie within --initial.spring-radius {cfg.initial.spring_radius} m of "
                         "each other and more than 0.1 mm apart (are they all at one point?); check "
                         "'particles', or raise the radius")
    inputs: dict = {}
    if cfg.ground:
        data, inputs["particles_below_ground"] = grounded(data)
        r = inputs["particles_below_ground"]
        if r["below"]:
            log(f"particles: {r['below']} of {r['of']} lie below the ground (the deepest "
                f"{1e3 * r['deepest']:.2f} mm), raised onto it")
    if cfg.smooth_inputs:
        data, smoothing = smoothed_inputs(data)
        inputs.update(smoothing)
        for name, r in smoothing.items():
            unit, k = ("rad", 1.0) if name == "tool_rotation" else ("mm", 1e3)
            if r["smoothed"]:
                log(f"input {name}: noise {k * r['noise']:.3g} {unit} per axis, smoothed before simulating "
                    f"(rms change {k * r['rms_change']:.3g} {unit})")
    topo = build_model(data, cfg.initial, SimParams(), cfg.device) if base is None and cfg.auto_substeps \
        else None
    rules: dict[tuple[float, int], SpringMassModel] = {}

    def topo_of(params: GlobalParams) -> SpringMassModel:
        """The springs that ``params`` simulate with (its radius rule's, where the springs are not given),
        for their stability bound: a denser set needs more substeps at the same stiffness."""
        key = (float(params.spring_radius), int(params.spring_max_neighbors))
        if data.springs is not None or key == (cfg.initial.spring_radius, cfg.initial.spring_max_neighbors):
            return topo
        if key not in rules:
            if len(rules) >= 64:  # a search that moves the radius makes a new rule each candidate
                rules.clear()
            rule = replace(cfg.initial, spring_radius=key[0], spring_max_neighbors=key[1])
            rules[key] = build_model(data, rule, SimParams(), cfg.device)
        return rules[key]

    def base_of(params: GlobalParams, y_top: float | None = None) -> SimParams:
        if topo is None:
            return base or cfg.base_params(data.fps)
        dash = max(params.dashpot_damping, cfg.initial.dashpot_damping)
        return cfg.base_params(data.fps, stable_substeps(topo_of(params), y_top or params.spring_Y, dash,
                                                         data.fps))

    base = base_of(cfg.initial)  # without automatic substeps, base_of gives this one from here on
    frame_dt = base.dt * base.substeps
    if abs(frame_dt * data.fps - 1.0) > 0.05:
        raise SysIdFormatError(f"{data.source}: field 'fps' is {data.fps} (frame {1 / data.fps:.5f} s) but "
                               f"the simulation frame is substeps * dt = {frame_dt:.5f} s; set substeps = "
                               f"round(1 / (fps * dt)) = {round(1 / (data.fps * base.dt))}")
    n_sel = selection_count(data, cfg.select_frames) if cfg.stage1 or cfg.stage2 else 0
    fit = fit_view(data, n_sel)
    sel = range(fit.train_frames.stop, data.train_frames.stop)
    loss = SequenceLoss(data, cfg.weights)
    model0 = build_model(data, cfg.initial, base, cfg.device)
    eval0 = evaluate(model0, data, loss)
    searched = tuple(cfg.cma.search) or applicable_parameters(data, base)

    runs: list[dict] = []
    ranges = parse_ranges(cfg.cma.ranges)
    grid = attachment_families(data, ranges)

    def stages(attach_grid: bool) -> dict | None:
        """Stages 1-3 from the initial values; ``attach_grid``: stage 1 scores the attachment families
        before its CMA-ES (otherwise after it). Returns the run's state (kept stage, its params and model,
        histories, notes); None when ``attach_grid``'s stage 1 ends where the first run's did (the rest
        would repeat it)."""
        notes: list[str] = []
        seconds: dict[str, float] = {}
        params = cfg.initial
        models = {"initial": model0}
        evals = {"initial": eval0}
        stage_params = {"initial": params}
        history1: list[dict] = []
        ident: dict[str, dict] = {}
        guesses: dict[str, dict] = {}
        if cfg.stage1:
            hand = params = within_ranges(params, searched, ranges)  # the hand-set values, inside the ranges
            start = params
            if cfg.guess:
                guesses = physical_guesses(fit, topo or models["initial"], params.control_radius)
                for name, g in guesses.items():
                    value = g["value"]
                    use = value is not None and name in searched and not (g.get("lower_bound")
                                                                           and value <= getattr(start, name))
                    if use:
                        start = within_ranges(replace(start, **{name: value}), (name,), ranges)
                        value = getattr(start, name)
                    g["used"] = bool(use)
                    log(f"guess {name}: {'-' if g['value'] is None else f'{value:.4g}'}"
                        f"{'' if use else ' (not used)'}: {g['from']}")
            fit_loss = SequenceLoss(fit, cfg.weights)
            t0 = time.perf_counter()
            by_rule = cfg.cma.topologies > 0 and "spring_radius" in searched  # the rule's sets, one by one
            params, history1 = (stage1_topologies if by_rule else stage1_cma)(
                fit, base, start, cfg.cma, cfg.weights, cfg.device, cfg.progress, log,
                base_of=base_of if topo is not None else None,
                walk=bool(guesses.get("spring_Y", {}).get("used")),
                candidates=() if start == hand else (hand,), attachments=grid if attach_grid else (),
                pool=pool)
            ident = identifiability(history1, ranges)
            found = params
            if cfg.keep_guess > 0:
                def score(p: GlobalParams) -> float:
                    return stage1_loss(fit, p, base_of(p), fit_loss, cfg.device)

                params = keep_unconstrained_guesses(params, start, guesses, ident, history1, cfg.keep_guess,
                                                    score, notes)
            if grid and not attach_grid and set(ATTACHMENT_NAMES) <= set(searched):
                # CMA-ES moved the attachment in steps of a quarter range: the families' sets, scored at its
                # end, are the attachment stage 2 fits the stiffness under
                names1 = tuple(n for n in searched if n in ATTACHMENT_NAMES
                               or (n == "spring_Y" and not ident.get(n, {}).get("guess_kept")))
                params, _ = stage1_cma(fit, base, params, replace(cfg.cma, search=names1), cfg.weights,
                                       cfg.device, False, lambda _m: None,
                                       base_of=base_of if topo is not None else None, attachments=grid,
                                       scan_stiffness=False, then_cma=False, pool=pool)
            seconds["stage1"] = time.perf_counter() - t0
            models["stage1"] = build_model(data, params, base_of(params), cfg.device)
            evals["stage1"] = evaluate(models["stage1"], data, loss)
            stage_params["stage1"] = params
            if found in (start, hand):
                notes.append(f"stage 1 did not improve on its start: none of {len(history1) - 1} candidates "
                             "beat the starting values (widen cma.ranges or check the data)")
        if attach_grid and cfg.stage1 and params == runs[0]["stage1"]:
            return None  # no attachment of the grid won: stage 1 ended as the first run's, so do the rest
        adam = cfg.adam
        if cfg.stage2 and adam.window > 0:
            adam = replace(adam, y_min=max(adam.y_min, params.spring_Y / adam.window),
                           y_max=min(adam.y_max, params.spring_Y * adam.window))
        history2: list[dict] = []
        history3: list[dict] = []
        regions = None
        rule = ("spring_Y", *RULE_NAMES)
        # the global parameters other than the spring rule, but a measured value that was kept stays
        names3 = tuple(n for n in applicable_parameters(data, base) if n not in rule
                       and (n in cfg.cma.search or not cfg.cma.search)
                       and not ident.get(n, {}).get("guess_kept"))
        hold_scale = bool(ident.get("spring_Y", {}).get("guess_kept"))
        if hold_scale and cfg.stage2:
            notes.append("stage 2 fits the stiffness pattern around the kept measured stiffness: the "
                         "object springs' mean log Y is held (the motion does not constrain its scale)")
        weights = cfg.weights
        for rnd in range(1, cfg.rounds + 1) if cfg.stage2 else ():
            what = "" if cfg.rounds == 1 else f" (round {rnd})"
            hold = None
            if rnd > 1:  # from the last round's stage 3: its stiffness pattern and global values
                if "stage3" not in models:
                    break
                hold = held_stiffness(models["stage3"])
                for k in ("stage2", "stage3"):  # the earlier rounds' stages stay, under their round's name
                    for d in (models, evals, stage_params):
                        d[f"{k}_round{rnd - 1}"] = d.pop(k)
            start2 = params if rnd == 1 else stage_params[f"stage3_round{rnd - 1}"]
            base2 = base_of(start2, adam.y_max) if topo is not None else base
            model = build_model(data, start2, base2, cfg.device, requires_grad=True, hold=hold)
            regions = spring_regions(model, adam.regions)  # as stage2_adam groups them (seeded k-means)
            if rnd == 1:
                weights = balanced_weights(cfg.weights, evals["stage1" if cfg.stage1 else "initial"].terms,
                                           adam.acc_share, log)
            t0 = time.perf_counter()
            _, rows = stage2_adam(model, data, adam, weights, cfg.progress, log, select=n_sel,
                                  hold_scale=hold_scale)
            first = rows[0]["train_loss"]
            if len(rows) > 1 and not any(r.get("train_loss", math.inf) < first for r in rows[1:]):
                notes.append(f"stage 2{what} did not improve on its start's fitted loss")
            seconds["stage2"] = seconds.get("stage2", 0.0) + time.perf_counter() - t0
            epoch0 = history2[-1]["epoch"] + 1 if history2 else 0
            history2 += [r | {"round": rnd, "epoch": epoch0 + r["epoch"]} for r in rows]
            c = model.contact_coeffs.numpy().astype(np.float64)
            fitted = fitted_contacts(model) if cfg.adam.fit_contact else []
            stage_params["stage2"] = replace(start2, **{CONTACT_NAMES[i]: float(c[i]) for i in fitted})
            models["stage2"] = model
            evals["stage2"] = evaluate(model, data, loss)
            if not (cfg.stage3 and names3):
                break
            hold = held_stiffness(models["stage2"])
            y_top = float(np.exp(models["stage2"].log_y_np.astype(np.float64).max()))

            def base3(p: GlobalParams, y_top: float = y_top) -> SimParams:
                return base_of(p, y_top)

            t0 = time.perf_counter()
            cma3 = replace(cfg.cma, search=names3, budget=cfg.stage3_budget, patience=0)
            params3, rows = stage1_cma(fit, base, stage_params["stage2"], cma3, cfg.weights, cfg.device,
                                       cfg.progress, log, base_of=base3, hold=hold, stage=f"stage 3{what}",
                                       attachments=grid, pool=pool)
            ident.update(identifiability(rows, ranges))  # the last round's
            seconds["stage3"] = seconds.get("stage3", 0.0) + time.perf_counter() - t0
            if params3 == stage_params["stage2"]:
                notes.append(f"stage 3{what} did not improve on stage 2's global parameters ({len(rows) - 1} "
                             "candidates)")
            count0 = history3[-1]["evaluation"] + 1 if history3 else 0
            history3 += [r | {"round": rnd, "evaluation": count0 + r["evaluation"]} for r in rows]
            models["stage3"] = build_model(data, params3, base3(params3), cfg.device, hold=hold)
            evals["stage3"] = evaluate(models["stage3"], data, loss)
            stage_params["stage3"] = params3
        history4: list[dict] = []
        last = "stage3" if "stage3" in models else "stage2"
        if cfg.stage2 and cfg.stage4 and regions is not None and by_region(models["stage2"], regions):
            hold4 = held_stiffness(models[last])
            t0 = time.perf_counter()
            names4 = tuple(n for n in names3 if n not in ATTACHMENT_NAMES)
            params4, hold4, history4 = stage4_cma(
                fit, stage_params[last], hold4, regions[:len(hold4[0])], names4, cfg.cma, cfg.stage4_budget,
                base_of,
                cfg.weights, cfg.device, hold_scale=hold_scale,
                y_bounds=(adam.y_min, adam.y_max), progress=cfg.progress, log=log, pool=pool)
            seconds["stage4"] = time.perf_counter() - t0
            if len(history4) < 2 or min(r["loss"] for r in history4[1:]) >= history4[0]["loss"]:
                notes.append(f"stage 4 did not improve on {last.replace('stage', 'stage ')}'s values "
                             f"({len(history4) - 1} candidates)")
            y_top = float(np.exp(max(hold4[0].max(), hold4[1])))
            models["stage4"] = build_model(data, params4, base_of(params4, y_top), cfg.device, hold=hold4)
            evals["stage4"] = evaluate(models["stage4"], data, loss)
            stage_params["stage4"] = params4
        kept, selection = _choose_stage(evals, sel, notes)
        return {"kept": kept, "selection": selection, "params": stage_params[kept], "model": models[kept],
                "evals": evals, "history1": history1, "history2": history2, "history3": history3,
                "history4": history4,
                "seconds": seconds, "notes": notes, "ident": ident, "regions": regions, "guesses": guesses,
                "stage1": stage_params.get("stage1")}

    # a generation's candidates at once in worker processes (stages 1, 3 and 4 of both starts)
    pools = CandidatePool(fit, cfg.weights, cfg.device, cfg.cma.workers) if cfg.cma.workers > 1 else \
        contextlib.nullcontext()  # (its processes start at its first batch: none when no stage searches)
    with pools as pool:
        runs.append(stages(False))
        floor = CHI3_MEAN * track_noise(fit)
        first_error = runs[0]["evals"][runs[0]["kept"]].train_error
        if cfg.stage1 and cfg.attachment_starts and data.num_controls and \
                set(ATTACHMENT_NAMES) <= set(searched):
            if not first_error <= cfg.second_start_over_floor * floor:  # NaN / inf included
                log("start 2 of 2: the stages again, stage 1 scoring the control attachments before its "
                    f"search (training tracking error {1e3 * first_error:.2f} mm, over "
                    f"{cfg.second_start_over_floor:g}x the tracks' noise floor {1e3 * floor:.2f} mm)")
                t0 = time.perf_counter()
                second = stages(True)
                if second is None:
                    runs[0]["seconds"]["other_start"] = time.perf_counter() - t0
                    log("start 2 of 2: stage 1 ended where the first run's did; the first run stands")
                    runs[0]["selection"]["second_start"] = (
                        "run to the end of stage 1, which ended where the first run's did (no attachment "
                        "scored first led elsewhere): the first run's training tracking error "
                        f"{1e3 * first_error:.2f} mm is over {cfg.second_start_over_floor:g}x the tracks' "
                        f"noise floor {1e3 * floor:.2f} mm")
                else:
                    runs.append(second)
            else:
                runs[0]["selection"]["second_start"] = (
                    f"not run: the training tracking error {1e3 * first_error:.2f} mm is within "
                    f"{cfg.second_start_over_floor:g}x the tracks' noise floor {1e3 * floor:.2f} mm")
    errors = [r["evals"][r["kept"]].train_error for r in runs]
    errors = [e if math.isfinite(e) else math.inf for e in errors]
    run = runs[int(np.argmin(errors))]
    kept, selection, params, model = run["kept"], run["selection"], run["params"], run["model"]
    evals, notes, seconds, regions = run["evals"], run["notes"], run["seconds"], run["regions"]
    history1, history2, history3, history4 = (run[f"history{k}"] for k in range(1, 5))
    ident, guesses = run["ident"], run["guesses"]
    if len(runs) > 1:
        selection["second_start"] = (f"run: the first run's training tracking error {1e3 * first_error:.2f} "
                                     f"mm is over {cfg.second_start_over_floor:g}x the tracks' noise floor "
                                     f"{1e3 * floor:.2f} mm")
        starts = ("search, then attachments", "attachments, then search")
        selection["starts"] = [{"stage1": what, "train_error_m": e, "kept": r is run}
                               for what, e, r in zip(starts, errors, runs, strict=True)]
        other = runs[1 - runs.index(run)]
        seconds["other_start"] = float(sum(other["seconds"].values()))
        if run is runs[1]:
            notes.append(f"the second start is kept: with stage 1 scoring the control attachments before its "
                         f"search the fit tracks the training frames to {1e3 * errors[1]:.2f} mm against "
                         f"{1e3 * errors[0]:.2f} mm (the attachment changes the motion in steps that one "
                         "search does not cross)")
    region_info: dict = {}
    if kept.split("_round")[0] not in ("stage2", "stage3", "stage4"):
        regions = None
    else:  # stage 2's regions over the kept model's springs (its own control springs: one region)
        n_obj, n3 = model.num_object_springs, model.num_springs
        regions = np.arange(n3) if len(np.unique(regions)) == len(regions) else \
            np.concatenate([regions[:n_obj], np.full(n3 - n_obj, regions[:n_obj].max() + 1)])
    if regions is not None and by_region(model, regions):  # for the kept stage only: one rollout a region
        try:
            region_info = region_information(model, fit, regions)
        except SimulationDiverged:
            region_info = {}
    evals["final"] = evals[kept]
    if cfg.stage1 or (cfg.stage2 and cfg.stage3):  # the values a search chose (stage 3 keeps the spring rule)
        rule = () if cfg.stage1 else ("spring_Y", *RULE_NAMES)
        notes += range_edge_notes(params, [n for n in searched if n in applicable_parameters(data, base)
                                           and n not in rule], ranges)
    for note in notes:
        log(f"note: {note}")
    return SysIdResult(params, params.sim_params(model.params), model.log_y_np.copy(), model, evals, history1,
                       history2, seconds, cfg, notes, ident, regions, guesses, selection, region_info,
                       history3, inputs, history4)


RANGE_EDGE = 0.03
"""a searched value within this share of its range (normalised: log scale for stiffness) from an end is at
that end"""


def range_edge_notes(params: GlobalParams, names, ranges: dict[str, SearchRange]) -> list[str]:
    """A note naming the searched values of ``params`` that ended at an end of their search range, but for
    the ends that are physical limits (0 for friction, restitution and damping), the spring rule's
    neighbour count (at its top it limits nothing unless the radius holds more particles) and the control
    attachment (its families hold every attachment in the ranges, :func:`attachment_families`: a radius
    at its top goes with the count that binds, and the other way round)."""
    edges = []
    for name in names:
        if name in ATTACHMENT_NAMES or name == "spring_max_neighbors":
            continue
        r, value = ranges[name], float(getattr(params, name))
        u = r.encode(value)
        if u >= 1.0 - RANGE_EDGE or (u <= RANGE_EDGE and r.lo > 0.0):
            edges.append(f"{name} {value:.4g} ({'top' if u > 0.5 else 'bottom'} of [{r.lo:g}, {r.hi:g}])")
    if not edges:
        return []
    return [f"at an end of its search range: {', '.join(edges)}. A value pressed against its range "
            "either wants one past it (widen the range, --cma.ranges NAME=LO:HI, and see whether the fit "
            "improves) or stands in for something the model lacks (e.g. heavy drag damping hiding a wrong "
            "stiffness pattern); either way the value is not a measurement of it"]


CHI3_MEAN = 2.0 * math.sqrt(2.0 / math.pi)
"""mean length of a 3-D Gaussian noise vector over its per-axis standard deviation"""

SELECT_MARGIN = 0.02
"""an earlier stage replaces a later one only when its selection-frame error is this much (relative) lower:
within it the two are tied (e.g. an object at rest in the selection frames) and the later stage is kept"""


def _choose_stage(evals: dict[str, SequenceEval], sel: range, notes: list[str]) -> tuple[str, dict]:
    """The stage to keep (see :func:`identify`) and the record of the choice; appends notes when a stage
    is not kept or the kept one's validation error is worse than the previous stage's."""
    order = list(evals)  # initial, stage1, stage2: the order they ran
    kept = order[-1]
    if sel:
        errors = {name: frames_error(evals[name], sel) for name in order}
        for name in reversed(order[:-1]):
            if errors[name] < (1.0 - SELECT_MARGIN) * errors[kept]:
                kept = name
        span = f"{sel.start}-{sel.stop - 1}"
        record = {"frames": [sel.start, sel.stop - 1], "errors_m": errors, "kept": kept,
                  "rule": f"the stage with the lowest tracking error on frames {span} (the last "
                          f"training frames, held out from fitting) is kept, the later one within "
                          f"{SELECT_MARGIN:.0%}; the validation frames do not choose"}
        if kept != order[-1]:
            notes.append(f"{kept} is kept, not {order[-1]}: its tracking error on the selection frames "
                         f"{span} (held out from fitting) is {1e3 * errors[kept]:.2f} mm against "
                         f"{1e3 * errors[order[-1]]:.2f}")
    else:
        record = {"frames": [], "kept": kept, "rule": "no selection frames (select_frames 0 or under 4 "
                                                      "training frames): the last stage run is kept"}
    i = order.index(kept)
    if i > 0 and evals[kept].val_error > 1.005 * evals[order[i - 1]].val_error:  # worse by over 0.5 %
        prev = order[i - 1]
        notes.append(f"{kept} is kept, but its validation error {1e3 * evals[kept].val_error:.2f} mm is "
                     f"worse than {prev}'s {1e3 * evals[prev].val_error:.2f} mm (the validation frames do "
                     "not choose: the motion there differs from the fitted one)")
    return kept, record
