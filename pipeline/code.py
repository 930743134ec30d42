"""DVC stage `code`: see `adaptdiffuser code --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("code")
