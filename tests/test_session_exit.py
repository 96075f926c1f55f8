"""A process that used Zenoh ends cleanly, even when a callback thread is still ending.

zenoh-python runs Python callbacks in threads of their own; one still running when the
interpreter finalizes cannot take the GIL and aborts the process with "FATAL: exception
not rethrown" (seen in services and examples that had closed their session just before).
"""

import subprocess
import sys


def test_a_callback_thread_ending_at_exit_does_not_abort_the_process() -> None:
    done = subprocess.run([sys.executable, "-m", "tests.agent_helpers.late_callback"],
                          capture_output=True, text=True, timeout=30)
    assert done.returncode == 0, done.stderr[-2000:]
    assert "closed" in done.stdout
