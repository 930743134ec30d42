"""DVC stage `evaluate-unseen-control`: see `adaptdiffuser evaluate-unseen-control --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("evaluate-unseen-control")
