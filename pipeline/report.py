"""DVC stage `report`: see `adaptdiffuser report --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("report")
