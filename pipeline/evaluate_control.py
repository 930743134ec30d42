"""DVC stage `evaluate-control`: see `adaptdiffuser evaluate-control --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("evaluate-control")
