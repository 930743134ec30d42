"""DVC stage `evaluate-coin`: see `adaptdiffuser evaluate-coin --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("evaluate-coin")
