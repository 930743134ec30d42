"""DVC stage `evaluate`: see `adaptdiffuser evaluate --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("evaluate")
