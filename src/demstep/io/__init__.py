"""Readers and writers: assemblies (CSV, LIGGGHTS dumps, YADE text), VTK, checkpoints."""
