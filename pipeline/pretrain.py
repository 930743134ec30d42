"""DVC stage `pretrain`: see `adaptdiffuser pretrain --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("pretrain")
