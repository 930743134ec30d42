"""DVC stage `control`: see `adaptdiffuser control --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("control")
