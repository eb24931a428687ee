"""Multi-seed studies on Ray Tune: ``python -m sb3_detc.study run STUDY.yml --dir DIR``, ``evaluate``, ``report``.

Sweeps of independent jobs with resumable rows (the benchmark scripts'): :mod:`sb3_detc.study.sweep`.
"""
