"""The benchmarks, in one place: ``jitterguard bench <name>`` (:mod:`.cli`) runs each and prints JSON.

Tests never assert wall-clock times; what is timed here is reported, with the machine's load beside it.
"""
