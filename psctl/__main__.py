"""``python -m psctl ...``: the ``psctl`` command, where its script is not on PATH (a venv not
activated, a profiler: ``python -m cProfile -m psctl normals obj``)."""
from psctl._start import main

main(prog_name="psctl")  # messages and help name "psctl", as the installed command's do
