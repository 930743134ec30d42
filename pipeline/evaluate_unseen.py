"""DVC stage `evaluate-unseen`: see `adaptdiffuser evaluate-unseen --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("evaluate-unseen")
