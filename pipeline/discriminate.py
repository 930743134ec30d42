"""DVC stage `discriminate`: see `adaptdiffuser discriminate --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("discriminate")
