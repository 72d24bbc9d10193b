"""Plane-strain compression of an FCC array of equal spheres (paper Figs. 10-12).

Specimen and boundaries
-----------------------
150 spheres (Table I: K_n = K_s = 1e11, density 2000, radius 20, mu = 0.3) in FCC
packing with square layers normal to z, the loading axis; x is the extension direction
and y the zero-strain direction (Thornton 1979). The specimen is 6 layers of 5 x 5
spheres, alternately on the square grid and in its hollows (6 x 25 = 150).

The boundaries decide whether Thornton's homogeneous mechanism can develop: all eight
inclined contacts of every sphere slide together while the x contacts open, so that
eps_xx = -2 eps_zz and eps_yy = 0. Rigid side walls break this: the spheres against
them lack half their neighbours and can roll or slide alone, and another code found a
peak near 3.3 (3.9 with rotation blocked) instead of 4.88 with that layout. We
therefore keep rigid walls only where the paper loads the specimen and make the
lateral directions periodic, which is the infinite array of Thornton's analysis:

* z: rigid frictionless platens; the bottom one fixed, the top cap moving down at
  constant velocity in stage 2 (servo-controlled to the confining stress in stage 1).
  Frictionless, so the end layers can extend freely in x as the mechanism requires.
* x: periodic, its length servo-controlled to hold sigma_xx (Love stress of the
  contacts) at the confining stress -- the paper's servo side walls.
* y: periodic with fixed length in stage 2 (plane strain; the paper's fixed walls).

sigma_zz is measured on the top cap (wall force over the current cross-section),
sigma_xx from the contact forces (no wall there). The work of the moving cap and of
the servo-controlled periodic length are both in the energy ledger.

Stages
------
1. Isotropic confinement to ``confining_stress`` with mu = 0 and a small local
   damping, all three directions servo-controlled, cycled until the kinetic energy
   is below ``ke_tol`` times the strain energy (the paper: "very small, < 1e-5"; here
   made relative) and the stresses are within 0.5 % of the target. Stage 1 runs at
   alpha = 0.1 for every study value, so all runs start from the same state.
2. Damping 0, mu as given, the top cap moves down at a constant speed giving the
   axial strain rate ``strain_rate``; the default 1e-4 /T gives an inertial number
   I = eps_rate d sqrt(rho / sigma) ~ 2e-4 at 1e6 confining stress, well inside the
   quasi-static regime (I < 1e-3), and ~100 periods of the specimen's slowest
   vibration per percent of strain. The energy ledger is reset at its start.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from demstep.contact.laws import LinearSpring
from demstep.energy import EnergyMonitor
from demstep.engine import Damping, Simulation, TimeStep
from demstep.errors import InputError, SimulationDiverged
from demstep.particles import Particles
from demstep.walls import Wall

SQRT2, SQRT3 = math.sqrt(2.0), math.sqrt(3.0)


def thornton_peak_ratio(mu: float) -> float:
    """Thornton's (1979) peak sigma_zz / sigma_xx for FCC with square layers normal to
    the loading axis z, plane strain (y zero strain): 2 (sqrt3 + sqrt2 mu) / (sqrt3 -
    2 sqrt2 mu) (4.88 at mu = 0.3). Sliding on the eight inclined contacts
    n = (+-1/2, +-1/2, +-1/sqrt2) with eps_xx = -2 eps_zz."""
    if not (0 <= mu < SQRT3 / (2 * SQRT2)):
        raise InputError(f"mu: Thornton's mechanism needs 0 <= mu < {SQRT3 / (2 * SQRT2):.4f}, got {mu!r}")
    return 2.0 * (SQRT3 + SQRT2 * mu) / (SQRT3 - 2.0 * SQRT2 * mu)


def thornton_axisymmetric_ratio(mu: float) -> float:
    """Axisymmetric compression of the same array: 2 (1 + mu) / (1 - mu)."""
    return 2.0 * (1.0 + mu) / (1.0 - mu)


@dataclass
class FCCConfig:
    """Parameters of the FCC plane-strain test (defaults: the paper's Table I)."""

    mu: float = 0.3
    alpha: float = 0.05
    strain: float = 0.02            # final axial strain of stage 2
    k_n: float = 1.0e11             # [M/T^2]
    k_s: float = 1.0e11
    density: float = 2000.0         # [M/L^3]
    radius: float = 20.0            # [L]
    layers: int = 6
    per_side: int = 5
    confining_stress: float = 1.0e6  # [M/(L T^2)]
    strain_rate: float = 1.0e-4     # [1/T]
    stage1_alpha: float = 0.1
    stage1_damping: float = 0.2     # local (Cundall) damping in stage 1
    ke_tol: float = 1.0e-5
    records: int = 400              # history points over stage 2
    energy_eps: float = 1.0e-2
    rotation: bool = True
    boundary: str = "periodic"      # "periodic" (x, y, z) or "platens" (rigid z walls)

    def validate(self):
        for name in ("alpha", "strain", "k_n", "k_s", "density", "radius", "confining_stress",
                     "strain_rate", "stage1_alpha", "ke_tol", "energy_eps"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise InputError(f"{name}: must be a finite positive number, got {v!r}")
        thornton_peak_ratio(self.mu)
        if self.boundary not in ("periodic", "platens"):
            raise InputError(f"boundary: must be periodic or platens, got {self.boundary!r}")
        if self.per_side < 4 or self.layers < 2:
            raise InputError(f"per_side >= 4 and layers >= 2 needed, got {self.per_side}, {self.layers}")


def fcc_specimen(cfg: FCCConfig):
    """Sphere centres (layers of per_side^2 on a square grid of pitch 2r, odd layers in
    the hollows) and the periodic lengths in x and y."""
    r = cfg.radius
    pitch = 2.0 * r
    layer_gap = SQRT2 * r
    g = np.arange(cfg.per_side) * pitch
    xs, ys = np.meshgrid(g, g, indexing="ij")
    layers = []
    for k in range(cfg.layers):
        off = r if k % 2 else 0.0
        z = r + k * layer_gap
        layers.append(np.stack([xs.ravel() + off + r / 2, ys.ravel() + off + r / 2,
                                np.full(xs.size, z)], axis=1))
    x = np.concatenate(layers)
    length = cfg.per_side * pitch
    return x, length, r + (cfg.layers - 1) * layer_gap + r


@dataclass
class FCCResult:
    config: dict
    theory: float
    peak_ratio: float
    peak_strain: float
    max_energy_error: float
    status: str
    dt: float
    alpha_exact_rotation: float
    alpha_exact_translation: float
    alpha_element_coupled: float
    steps: int
    message: str = ""
    curves: dict = field(default_factory=dict)
    #: where the state was saved when the run diverged (None: it did not)
    diverged_state: str | None = None

    def summary(self) -> dict:
        """The documented JSON of ``demstep fcc --json``."""
        return {"mu": self.config["mu"], "alpha": self.config["alpha"],
                "peak_ratio": self.peak_ratio, "theory": self.theory,
                "max_energy_error": self.max_energy_error, "status": self.status}


def build_fcc(cfg: FCCConfig) -> Simulation:
    """The specimen before stage 1 (touching spheres, zero stress)."""
    x, length, height = fcc_specimen(cfg)
    p = Particles.from_density(x, np.full(len(x), cfg.radius), cfg.density)
    m = float(p.m[0])
    dt1 = cfg.stage1_alpha * math.sqrt(m / max(cfg.k_n, cfg.k_s))
    speed = 1e-4 * cfg.radius / dt1
    law = LinearSpring(k_n=cfg.k_n, k_s=cfg.k_s, mu=0.0, mu_wall=0.0)
    common = dict(damping=Damping(local=cfg.stage1_damping), rotation=cfg.rotation,
                  timestep=TimeStep.from_alpha(cfg.stage1_alpha),
                  energy=EnergyMonitor(eps=cfg.energy_eps, every=50))
    if cfg.boundary == "platens":
        walls = [Wall([0, 0, 0], [0, 0, 1], name="bottom"),
                 Wall([0, 0, height], [0, 0, -1], name="top", motion="servo",
                      target_stress=cfg.confining_stress, max_speed=speed)]
        sim = Simulation(p, law, walls=walls, periodic=[length, length, None], **common)
    else:
        # the layers repeat with period 2 x layer gap along z: an even number of layers
        if cfg.layers % 2:
            raise InputError(f"layers: a periodic FCC stack needs an even number, got {cfg.layers}")
        x[:, 2] -= cfg.radius - SQRT2 * cfg.radius / 2
        p = Particles.from_density(x, np.full(len(x), cfg.radius), cfg.density)
        sim = Simulation(p, law, periodic=[length, length, cfg.layers * SQRT2 * cfg.radius],
                         **common)
    axes = (0, 1) if cfg.boundary == "platens" else (0, 1, 2)
    for axis in axes:
        sim.set_box(axis, "servo", target_stress=cfg.confining_stress, max_speed=speed)
    return sim


def stresses(sim: Simulation):
    """(sigma_xx, sigma_yy, sigma_zz) of the specimen [M/(L T^2)], compression positive.

    Periodic: the Love-Weber average over the cell (the boundary traction of a periodic
    cell). Platens: sigma_zz on the top cap and the lateral stresses from the contacts
    of the layers between the platens (the Love sum over the volume of the inter-layer
    gaps), so that both are stresses of the same interior material."""
    love = sim.love_stress()
    if sim.walls:
        interior = SQRT2 * float(sim.r[0]) * (round(len(sim.r) / _layer_size(sim)) - 1)
        scale = float(sim.extents()[2]) / interior
        return float(love[0] * scale), float(love[1] * scale), float(sim.wall_stress()[1])
    return float(love[0]), float(love[1]), float(love[2])


def _layer_size(sim):
    return int(round(sim.extents()[0] / (2 * sim.r[0]))) ** 2


def run_stage1(cfg: FCCConfig, max_steps: int = 400_000) -> Simulation:
    """Isotropic confinement (mu = 0, small damping) until at rest at the target stress."""
    cfg.validate()
    sim = build_fcc(cfg)

    def settled(s):
        sx, sy, sz = stresses(s)
        ok = all(abs(v / cfg.confining_stress - 1) < 5e-3 for v in (sx, sy, sz))
        return ok and s.ledger.kinetic < cfg.ke_tol * s.ledger.strain

    sim.run(until=settled, max_steps=max_steps, check_every=200)
    if not settled(sim):
        raise RuntimeError(f"stage 1 did not settle within {max_steps} steps "
                           f"(stresses {stresses(sim)}, KE {sim.ledger.kinetic:.3g})")
    return sim


def run_stage2(sim: Simulation, cfg: FCCConfig, progress=None) -> FCCResult:
    """Plane-strain loading from a settled stage-1 simulation (modified in place)."""
    m = float(sim.m[0])
    unit = math.sqrt(m / max(cfg.k_n, cfg.k_s))
    # exact critical steps of the confined specimen (contacts as they are now)
    a_rot = sim.critical_dt("exact", rotation=True) / unit
    a_trans = sim.critical_dt("exact", rotation=False) / unit
    a_coupled = sim.critical_dt("element-coupled", rotation=True) / unit
    # stage 2 settings
    sim.law.mu = cfg.mu
    sim.damping = Damping()
    sim.timestep = TimeStep.from_alpha(cfg.alpha)
    sim.dt = None
    sim.set_box(1, "fixed")
    height0 = float(sim.extents()[2])
    if sim.walls:
        sim.set_wall_motion(1, "velocity", velocity=[0.0, 0.0, -cfg.strain_rate * height0])
    else:
        sim.set_box(2, "rate", rate=-cfg.strain_rate * height0)
    sim.monitor = EnergyMonitor(eps=cfg.energy_eps, every=20)
    sim.ledger.reset()
    sim.prepare()
    total_steps = int(math.ceil(cfg.strain / (cfg.strain_rate * sim.dt)))
    every = max(1, total_steps // cfg.records)
    curves = {k: [] for k in ("strain", "ratio", "sigma_xx", "sigma_yy", "sigma_zz",
                              "energy_error", "kinetic", "strain_energy", "external",
                              "friction", "time")}

    def record(s):
        sx, sy, sz = stresses(s)
        curves["strain"].append((height0 - float(s.extents()[2])) / height0)
        curves["ratio"].append(sz / sx if sx > 0 else np.nan)
        curves["sigma_xx"].append(sx)
        curves["sigma_yy"].append(sy)
        curves["sigma_zz"].append(sz)
        curves["energy_error"].append(s.ledger.balance_error())
        curves["kinetic"].append(s.ledger.kinetic)
        curves["strain_energy"].append(s.ledger.strain)
        curves["external"].append(s.ledger.external)
        curves["friction"].append(s.ledger.friction)
        curves["time"].append(s.time)
        if progress is not None:
            progress(s, curves)

    sim.every(every, record)
    status, message, saved = "stable", "", None
    try:
        sim.run(steps=total_steps)
    except SimulationDiverged as exc:
        status, message, saved = "unstable", str(exc), exc.checkpoint
        record(sim)
    arrays = {k: np.asarray(v, dtype=float) for k, v in curves.items()}
    ratio = arrays["ratio"]
    finite = np.isfinite(ratio)
    if status == "unstable":
        # a blow-up ends in garbage stresses: the peak is read before the last record
        finite[-1] = False
    peak_idx = int(np.nanargmax(np.where(finite, ratio, -np.inf))) if finite.any() else 0
    max_err = max(float(np.nanmax(arrays["energy_error"])) if len(ratio) else 0.0,
                  sim.monitor.max_error)
    if status == "stable" and max_err > cfg.energy_eps:
        status = "energy-warning"
    return FCCResult(config=asdict(cfg), theory=thornton_peak_ratio(cfg.mu),
                     peak_ratio=float(ratio[peak_idx]) if finite.any() else float("nan"),
                     peak_strain=float(arrays["strain"][peak_idx]) if len(ratio) else float("nan"),
                     max_energy_error=max_err, status=status, dt=float(sim.dt),
                     alpha_exact_rotation=float(a_rot), alpha_exact_translation=float(a_trans),
                     alpha_element_coupled=float(a_coupled), steps=sim.step, message=message,
                     curves=arrays, diverged_state=saved)


def run_fcc(cfg: FCCConfig, stage1: Simulation | None = None, progress=None,
            checkpoint_dir=None) -> FCCResult:
    """Both stages. ``stage1`` (a settled simulation, copied from a checkpoint) skips
    stage 1. ``checkpoint_dir``: where the state is saved if the run diverges (None:
    the engine's default, the system's temporary folder); the result's
    ``diverged_state`` names the file."""
    cfg.validate()
    sim = stage1 if stage1 is not None else run_stage1(cfg)
    if checkpoint_dir is not None:
        sim.checkpoint_dir = checkpoint_dir
    return run_stage2(sim, cfg, progress=progress)
