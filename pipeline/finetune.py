"""DVC stage `finetune`: see `adaptdiffuser finetune --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("finetune")
