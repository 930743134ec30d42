"""DVC stage `summarize`: see `adaptdiffuser summarize --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("summarize")
