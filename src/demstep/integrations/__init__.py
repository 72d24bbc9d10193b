"""The certificate inside the codes people run.

* :mod:`demstep.integrations.lammps_model`: LAMMPS' ``pair_style granular`` coefficients
  (the text of a ``pair_coeff`` line) as the contact springs and dashpots the
  certificate takes (``demstep dt --lammps-model``);
* :mod:`demstep.integrations.lammps`: the step of a running LAMMPS instance certified
  and set, from a Python-driven run or from ``fix python/invoke``
  (LAMMPS' Python module from Debian's ``python3-lammps`` and ``liblammps-dev``: no
  extra to install from pip);
* :mod:`demstep.integrations.yade`: the step of a running YADE scene certified and set
  from a ``PyRunner`` in ``O.engines`` (YADE's own Python, in a venv that sees
  Debian's packages and demstep: docs/yade.md).
"""
