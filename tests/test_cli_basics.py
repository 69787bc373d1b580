import subprocess
import sys


def test_help_lists_and_exits_zero():
    out = subprocess.run([sys.executable, "-m", "crater_thermal", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "crater" in out.stdout.lower()


def test_unknown_command_exits_2_without_traceback():
    out = subprocess.run([sys.executable, "-m", "crater_thermal", "no-such-command"], capture_output=True, text=True)
    assert out.returncode == 2
    assert "Traceback" not in out.stderr
