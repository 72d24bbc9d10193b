"""Checks of a checkpoint's arrays before a Simulation restores them.

The compiled kernels do not check bounds: a short array or an index out of range would
be read past its end. :func:`checked_state` looks at every array of a
:meth:`demstep.engine.Simulation.state_dict` read back (shapes against this
Simulation's, index ranges, finite values) and names the array and the value at fault.
"""

from __future__ import annotations

import math

import numpy as np

from demstep.engine.auto_step import AutoStep
from demstep.errors import InputError
from demstep.state import CONTACT_HISTORY, Meshes

#: fields of the pair and particle-wall lists: one row per listed contact (``roll``
#: and ``cover`` may have none: no rolling resistance, no cover tracked)
LIST_FIELDS = {"pairs": ("i", "j") + CONTACT_HISTORY,
               "wall_state": ("p", "wall") + CONTACT_HISTORY,
               "meshes": ("cand_p", "cand_t") + Meshes.SLOTS}

#: the Simulation's scalars in a checkpoint, each an array ``scalars.<name>`` of one
#: value (a checkpoint of format 3 held them in one array ``scalars``, in this order):
#: step, time [T], the step dt and the last one taken [T], whether the first step (the
#: half backward kick) is to come, the energy monitor's largest error, the 'auto'
#: control's next scheduled estimate and its last estimate [T], and (step, time, dt)
#: when dt last changed (the clock counts from there)
SCALARS = ("step", "time", "dt", "dt_prev", "first_step_pending", "max_energy_error",
           "next_dt_update", "dt_estimate", "time_ref_step", "time_ref_time", "time_ref_dt")
#: the scalars that are NaN when unset
NAN_SCALARS = ("dt", "dt_estimate", "time_ref_dt")


def scalar_arrays(data: dict) -> dict:
    """``data`` with a format-3 array ``scalars`` spread into the named ``scalars.*``."""
    if "scalars" in data and f"scalars.{SCALARS[0]}" not in data:
        data = dict(data)
        values = np.asarray(data.pop("scalars")).reshape(-1)
        if values.shape != (len(SCALARS),):
            raise InputError(f"checkpoint array 'scalars' has shape {values.shape}, expected "
                             f"({len(SCALARS)},)")
        data.update({f"scalars.{name}": values[k:k + 1] for k, name in enumerate(SCALARS)})
    return data


def checked_state(sim, data: dict, source: str) -> dict:
    """``data`` (a :meth:`state_dict` read back) checked before anything is restored:
    every per-particle, per-wall and per-body array has the shape this Simulation
    (built from the same case) has, every pair, wall-contact and bond array as many
    rows as its list has, indices lie in range and values are finite (the compiled
    kernels do not check bounds: a short array would be read past its end). Raises
    an InputError naming ``source``, the array's key and the shape or value; returns
    the arrays as contiguous arrays of the engine's types."""
    n, n_walls = len(sim.r), len(sim.wall_state.point)
    data = dict(data)
    # another case's checkpoint: say so, not which array differs first
    for key, like, what in (("r", sim.r, "particles"), ("wall_state.point",
                            sim.wall_state.point, "walls"), ("bodies.x", sim.bodies.x,
                            "bodies")):
        shape = np.shape(data[key])
        if shape != like.shape:
            raise InputError(f"{source}: the checkpoint's {what} do not match the "
                             f"simulation ({shape[0] if shape else 0} in the checkpoint, "
                             f"{len(like)} in the case)")

    def fail(key, what):
        return InputError(f"{source}: checkpoint array {key!r} {what}")

    def numbers(key, like=None):
        a = np.asarray(data[key])
        kinds = "iu" if like is not None and like.dtype.kind in "iu" else "fiu"
        if a.dtype.kind not in kinds:
            what = "integers" if kinds == "iu" else "numbers"
            raise fail(key, f"holds {a.dtype} values, not {what}")
        if like is not None:
            a = np.ascontiguousarray(a, dtype=like.dtype)
        data[key] = a
        return a

    def shaped(key, shape, count=""):
        a = data[key]
        if a.shape != tuple(shape):
            raise fail(key, f"has shape {a.shape}, expected {tuple(shape)}{count}")

    def in_range(key, top, what, a=None):
        a = data[key] if a is None else a
        if a.size and (a.min() < 0 or a.max() >= top):
            value = a.min() if a.min() < 0 else a.max()
            raise fail(key, f"holds the {what} index {int(value)}, outside 0..{top - 1}")

    def finite(key, nan_only=False):
        a = data[key]
        if a.dtype.kind == "f":
            bad = np.isnan(a) if nan_only else ~np.isfinite(a)
            if bad.any():
                at = np.unravel_index(int(np.argmax(bad)), a.shape)
                raise fail(key, f"holds the non-finite value {a[at]} at {list(map(int, at))}")

    counts = {"spheres": f" ({n} particles)", "wall_state": f" ({n_walls} walls)",
              "bodies": f" ({sim.bodies.n} bodies)", "box": "",
              "meshes": f" ({sim.meshes.n} meshes, {len(sim.meshes.tri)} triangles)"}
    for name in sim.BUNDLES:
        bundle = getattr(sim, name)
        lists = LIST_FIELDS.get(name, ())
        if name == "bonds":
            lists = bundle.STATE
        if lists:
            head = f"{name}.{lists[0]}"
            rows = len(numbers(head, getattr(bundle, lists[0])).reshape(-1))
        for f in bundle.STATE:
            key = f"{name}.{f}"
            like = getattr(bundle, f)
            a = numbers(key, like)
            if f in lists:
                expected = (rows,) + like.shape[1:]
                optional = f in ("roll", "cover") and a.shape[0] == 0
                if not optional:
                    shaped(key, expected, f" (as many rows as {head}: {rows})")
                elif a.shape[1:] != like.shape[1:]:
                    raise fail(key, f"has shape {a.shape}, expected {expected}")
            else:
                shaped(key, like.shape, counts[name])
            # (inf is a value of: unused servo limits, the cover of a contact covered
            # at any overlap, a bond without a strength limit)
            finite(key, nan_only=f in ("servo", "cover", "sigma_c", "tau_c", "cover_ctl"))
    for key in ("pairs.i", "pairs.j", "wall_state.p", "bonds.i", "bonds.j", "meshes.cand_p"):
        in_range(key, n, "particle")
    for key in ("meshes.cand_t", "meshes.slot_tri"):
        in_range(key, len(sim.meshes.tri), "triangle")
    in_range("meshes.slot_mesh", max(1, sim.meshes.n), "mesh")
    in_range("wall_state.wall", n_walls, "wall")
    for key, like in (("ledger.acc", sim.ledger.acc), ("ledger.energy", sim.ledger.energy),
                      ("ledger.counters", sim.counters)):
        a = numbers(key, like)  # (older checkpoints: a prefix of the layout)
        if a.ndim != 1 or len(a) > len(like):
            raise fail(key, f"has shape {a.shape}, expected at most ({len(like)},)")
        finite(key)
    numbers("gravity", sim.gravity)
    shaped("gravity", sim.gravity.shape)
    finite("gravity")
    for name in SCALARS:
        key = f"scalars.{name}"
        value = numbers(key).astype(np.float64)
        data[key] = value
        shaped(key, (1,))
        if not (math.isfinite(value[0]) or (name in NAN_SCALARS and math.isnan(value[0]))):
            raise fail(key, f"holds the non-finite value {value[0]}")
        if name in ("step", "time") and value[0] < 0:
            raise fail(key, f"holds a negative {name}, got {value[0]:g}")
    for key in ("monitor", "last_sort"):
        if key in data:
            a = numbers(key).reshape(-1)
            if a.size == 0:
                raise fail(key, "is empty")
            finite(key)
    if "ts_cert" in data:
        AutoStep.check_certificate_state(data, numbers, in_range, finite, fail, n, n_walls,
                                         sim.bodies.n)
    sim.auto.check_added_record(data, fail)
    return data
