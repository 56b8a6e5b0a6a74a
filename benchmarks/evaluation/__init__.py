"""Every network scenario of the thesis in one run, next to ZeroMQ and Zenoh (docs/evaluation.md).

Run ``python -m benchmarks.evaluation --help`` (needs root: the network emulator).
* :mod:`.sweep`: the rows and scenarios, measured; :mod:`.policies`: the channel-policy rows;
* :mod:`.report`: docs/evaluation.md and the raw summaries; :mod:`.plot`: its figures.
"""
