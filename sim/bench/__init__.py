"""``bess-ded bench``: micro-benchmarks (``micro``) and real-time figures of
multi-process bus runs (``realtime``)."""
