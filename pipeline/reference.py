"""DVC stage `reference`: see `adaptdiffuser reference --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("reference")
