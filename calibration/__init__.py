"""Elastoprobe calibration: F/T payload, probe tip, scanner mount, object registration.

Entry points (import the modules; nothing heavy is imported here):
- ``runner.run_calibration(kind, cell_path, seed, out_path) -> dict`` (the CLI's ``calibrate``)
- ``calfile.check_calibration(cell_spec, cell_path) -> list[str]`` and
  ``calfile.load_calibration(path) -> Corrections`` (``Corrections.apply_to(cell_spec)``)
- ``ft_payload.GravityCompensator`` for removing the payload's weight from a stream
See docs/calibration.md.
"""
