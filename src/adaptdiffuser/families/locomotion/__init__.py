"""The MuJoCo locomotion family (Hopper, Walker2d, HalfCheetah, gymnasium ``*-v5``): the simulator, the D4RL
score reference and the regenerated D4RL-style datasets (behaviour policies trained with stable-baselines3).

Nothing heavy is imported here: import the submodules (``simulator``, ``reference``, ``behaviour``, ``controller``)
directly.
"""
