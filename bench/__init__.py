"""The benches: scripts that measure the product (``python bench/NAME.py``, one JSON on stdout)
and the helpers they share, importable as ``bench.NAME`` (the tests import them so; pytest puts
the repository's root on the path, pyproject.toml ``pythonpath``).

Not part of the installed product: nothing under controller/, sim/ or calibration/ imports it.
"""
