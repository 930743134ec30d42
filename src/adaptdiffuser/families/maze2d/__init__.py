"""Maze2D: point-mass navigation in D4RL's U-Maze, Medium and Large mazes (and custom layouts), with the unseen
gold-coin task. Registered in ``family_registry.py``; ``params.py`` holds its task model and ``family.py`` what
the generic pipeline asks of it. The rest: ``simulator.py`` (PointMaze with the protocol, expert and tracker),
``layouts.py`` (mazes as data), ``expert.py`` (the waypoint-expert dataset), ``execution.py`` (plan following),
and for the evolution and gold-coin stages ``tasks.py`` (generation tasks), ``selection.py`` (the paper's
selection rule, the coin check) and ``gold_coin.py`` (the fixed coin cases and their scoring).
"""
