"""The web viewer (viser): a run folder's map, trajectories and factor graph, afterwards or live during a run.

``layers`` reads a run folder into plain arrays (no viser); ``scene`` draws them in a viser server; ``frames``
renders the slider's views; ``app`` serves a finished run (``ggfslam view``); ``live`` follows a running system
(``ggfslam run --view``). Nothing in a run imports this package unless ``--view`` asks for it.
"""
