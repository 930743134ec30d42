"""DVC stage `generate`: see `adaptdiffuser generate --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("generate")
