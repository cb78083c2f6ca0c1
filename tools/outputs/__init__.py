"""What the commands write for people and other tools: the bench report (``report``,
``faultreport``), strict JSON (``jsonout``), the pose table (``posecsv``), plots (``plot``),
OpenIGTLink (``igtl``), bus captures (``buscapture``), and ``sinks``, which opens the
``--igtl``, ``--capture``, ``--poses`` and ``--plot`` outputs of a run."""
