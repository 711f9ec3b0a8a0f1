"""Where frames come from at run time: sources that deliver frames on their own clock, as a sensor driver does.

- ``realsense``: an Intel RealSense camera or recording through pyrealsense2 (``realsense.py``);
- ``folder``: a folder that another program fills (``folder.py``);
- ``replay``: a dataset folder delivered at its timestamps' pace, so a replay shows what a live run on this machine
  would do (``replay.py``).

Each delivers into a small newest-wins queue (``base.py``): frames arriving while the system is busy are dropped.
"""
