"""DVC stage `import-data`: see `adaptdiffuser import-data --help`."""

from adaptdiffuser.cli import run_stage

if __name__ == "__main__":
    run_stage("import-data")
