"""``iscd eval``: simulated sweeps of communication and ranging, scored against ground truth,
and the report beside the dissertation's numbers (docs/eval.md).

- :mod:`.metrics`   pure scoring: symbol/bit errors, (4.4) throughput, goodput, range errors
- :mod:`.sweeps`    one simulated point: render, decode with the real receiver, score
- :mod:`.suites`    the comms / hdr / ranging / motion suites and running them
- :mod:`.oracle`    decodings with parts of the receiver replaced by the truth (issue 12): the
                    SER split into following, timing, channel and the floor, error profiles
- :mod:`.reference` the dissertation's results (SPEC section 5)
- :mod:`.report`    Markdown + PNG plots + results.json
"""
