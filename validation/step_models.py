"""How much rolling resistance and parallel bonds lower the critical step, and how far
rules that look at k_n (and k_t) only are off.

For pre-compressed periodic lattices (FCC and BCC spheres, hexagonal disks; linear
springs k_n = k_t, rotation free), each model's exact critical step (the certified
eigenvalue computation with every spring of the model) is compared with the exact step
of the contact springs alone and with the usual rules computed from the contact
springs (the nodal rule, YADE-style; Itasca's sqrt(m/k)); a ratio above 1 means the
rule would step above the model's critical step (unstable). Parameters as users set
them: rolling resistance in LIGGGHTS' epsd convention with mu_r 0.1 and 0.3, YADE-style
stiffness factors beta_r = beta_w = 1 and 2, and parallel bonds whose normal spring
k_n^b A equals 1 or 3 times the contact's k_n (radius multiplier 1).

    python validation/step_models.py > docs/step-models-table.md
"""

from __future__ import annotations

import math

from demstep.contact.bonds import ParallelBonds
from demstep.experiments.stability import build_specimen
from demstep.timestep.estimates import estimate_time_steps

K = 1.0e6
MODELS = [
    ("rolling epsd, mu_r = 0.1", dict(rolling_convention="epsd", rolling_friction=0.1), None),
    ("rolling epsd, mu_r = 0.3", dict(rolling_convention="epsd", rolling_friction=0.3), None),
    ("rolling + twisting beta = 1", dict(rolling_convention="beta", rolling_stiffness=1.0,
                                         twisting_stiffness=1.0), None),
    ("rolling + twisting beta = 2", dict(rolling_convention="beta", rolling_stiffness=2.0,
                                         twisting_stiffness=2.0), None),
    ("bonds, k_n^b A = k_n", None, 1.0),
    ("bonds, k_n^b A = 3 k_n", None, 3.0),
]


def main():
    print("| lattice | model | exact dt / exact dt of the contact springs | nodal rule (contact springs) / exact | Itasca sqrt(m/k_n) / exact |")
    print("|---|---|---:|---:|---:|")
    for name in ("fcc", "bcc", "hex"):
        plain = build_specimen(name, 0.1, k=K)
        plain.prepare()
        base = estimate_time_steps(plain.particles_now(), plain.contact_set(), rotation=True,
                                   methods=("exact", "nodal", "itasca"))
        dt_plain = base.get("exact").dt
        nodal, itasca = base.get("nodal").dt, base.get("itasca").dt
        area = math.pi if plain.dim == 3 else 2.0  # bond section at radius ~1
        for label, options, bond_ratio in MODELS:
            bonds = None if bond_ratio is None else ParallelBonds(normal_stiffness=bond_ratio * K / area)
            sim = build_specimen(name, 0.1, k=K, law_options=options, bonds=bonds)
            sim.prepare()
            dt = sim.critical_dt("exact")
            print(f"| {name} | {label} | {dt / dt_plain:.3f} | {nodal / dt:.2f} | {itasca / dt:.2f} |")


if __name__ == "__main__":
    main()
