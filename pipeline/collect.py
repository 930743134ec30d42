"""DVC stage `collect`: see `adaptdiffuser collect --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("collect")
