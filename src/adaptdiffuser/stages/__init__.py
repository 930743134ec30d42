"""What each pipeline stage does, one module per stage, over a project directory.

Stage entry points (``pipeline/*.py`` and the ``adaptdiffuser`` CLI) only parse arguments and call these, and
each stage's ``deps`` in ``dvc.yaml`` lists exactly its own module and what that module uses.
"""
