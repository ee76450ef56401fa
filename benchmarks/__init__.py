"""Benchmarks (`make bench`). Each ``bench_<area>.py`` defines ``run(quick: bool) -> list[Result]``.

Speed targets are ratios against a reference measured in the same run (a plain numpy matrix product,
plain rosbags iteration, the OctoMap library), never absolute timings asserted in unit tests.
"""
