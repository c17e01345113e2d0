"""The render stage's backends: ``tiny`` (pybullet's TinyRenderer) and ``cycles`` (Blender).

``blender_job.py`` is not a module of the host: it is the script that Blender's own Python
runs (``python -P blender_job.py JOB_DIR``), shipped as package data beside ``cycles.py``.
"""
