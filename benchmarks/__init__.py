"""Speed and memory benchmarks of sb3-sfgpi, each against a baseline measured in the same run.

Run them all with ``python -m benchmarks`` (``--quick`` for a run under two minutes); see ``__main__.py``.
"""
