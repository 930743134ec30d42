"""DVC stage `import-model`: see `adaptdiffuser import-model --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("import-model")
