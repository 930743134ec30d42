"""The KUKA family: a KUKA iiwa arm with a suction cup and four blocks on PyBullet; block stacking is the seen task
(scripted demonstrations) and pick-and-place at four marked locations the unseen one.

Nothing heavy is imported here: import the submodules (``scene``, ``simulator``, ``demonstrator``) directly.
"""
