"""A process whose Zenoh callback thread is still ending when Python finalizes.

The callback runs in a daemon thread (declared from one); a gc callback wakes it during the
interpreter's last collection, the moment it could no longer take the GIL, unless uma's exit
hook waited for it.  Exit status 0 when the process ended cleanly.
"""
import gc
import sys
import threading
import time

from agent.runtime.session import close_session, open_session

session = open_session("peer", ["tcp/127.0.0.1:0"])
inside, finalizing = threading.Event(), threading.Event()


def callback(sample: object) -> None:
    inside.set()
    finalizing.wait(0.5)          # ends on its own, or when Python finalizes


def wake_callback_while_finalizing(phase: str, info: dict, sys=sys, time=time) -> None:
    if sys.is_finalizing():
        finalizing.set()
        time.sleep(0.2)           # let the callback thread try to take the GIL now


def declare() -> None:            # from a daemon thread: Zenoh's callback thread is one too
    kept.append(session.declare_subscriber("exit/case", callback))


kept: list = []
worker = threading.Thread(target=declare, daemon=True)
worker.start()
worker.join()
session.put("exit/case", b"x")
assert inside.wait(5.0), "the callback never ran"
close_session(session)
gc.callbacks.append(wake_callback_while_finalizing)
print("closed", flush=True)
