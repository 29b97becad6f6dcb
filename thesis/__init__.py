"""Reproduction of the thesis's chapters 3-4 (figures and `docs/thesis/REPORT.md`), built on the
`timewarp` library. Lives in the source checkout only: `python -m thesis.reproduce`."""
