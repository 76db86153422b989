"""Helper of the CLI tests: run `pisml` as a user does, in a subprocess."""
import subprocess
import sys


def pisml(*args, check=True):
    proc = subprocess.run([sys.executable, "-m", "pisml_ros.cli", *map(str, args)], capture_output=True, text=True,
                          timeout=300)
    if check and proc.returncode != 0:
        raise AssertionError(f"pisml {' '.join(map(str, args))} failed ({proc.returncode}): {proc.stderr}")
    return proc
