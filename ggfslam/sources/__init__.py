"""Where frames come from at run time: sources that deliver frames on their own clock, as a sensor driver does.

``replay``: a dataset folder delivered at its timestamps' pace into a small newest-wins queue, so a replay shows
what a live run on this machine would do (frames arriving while the system is busy are dropped).
"""
