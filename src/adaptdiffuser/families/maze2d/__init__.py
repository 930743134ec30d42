"""Maze2D: point-mass navigation in D4RL's U-Maze, Medium and Large mazes (and custom layouts), with the unseen
gold-coin task. Registered in ``families/registry.py``; ``params.py`` holds its task model, ``family.py`` the rest.
"""
