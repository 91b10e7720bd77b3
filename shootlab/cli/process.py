"""The process of one ``shootlab`` command: set up for a single command, ended as soon as it is done.

A command's wall time is mostly fixed costs around a few seconds of numerics (the confined
compression, 20 elements, 201 points: solve 2.6 s of a 7.8 s command).  :func:`run` spends
less on two of them:

* **Threads.**  A library user's process runs torch on one thread (``shootlab/__init__.py``): many
  of them may share a machine.  A command owns its process, so it uses every core the process may
  run on (Newton solve of the confined compression: 2.6 s on one thread, 2.0 s on two).
  ``SHOOTLAB_NUM_THREADS`` still decides where it is set.
* **The interpreter's teardown** (:func:`leave`, about 0.9 s).
"""
from __future__ import annotations

import atexit
import os
import sys
from typing import Callable, NoReturn


def cores() -> int:
    """The number of cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:          # macOS, Windows
        return os.cpu_count() or 1


def prepare() -> None:
    """torch on every core of the process, unless ``SHOOTLAB_NUM_THREADS`` says otherwise."""
    import torch

    if not os.environ.get("SHOOTLAB_NUM_THREADS"):
        torch.set_num_threads(cores())


def leave(code: int) -> NoReturn:
    """End the process with exit status ``code`` once the atexit handlers have run and stdout and
    stderr are flushed, without the interpreter's teardown.  After a command, tearing down the
    modules (torch's above all) takes about 0.9 s and does nothing that a finished command needs:
    its files are closed and its output folder is in place."""
    atexit._run_exitfuncs()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except (OSError, ValueError):       # a closed pipe or stream: nothing more can be said there
            pass
    os._exit(code)


def run(main: Callable[[], int]) -> NoReturn:
    """``main()`` in a process set up for it (:func:`prepare`), then :func:`leave` with its status
    (that of a ``SystemExit`` too, e.g. after ``--help``)."""
    prepare()
    try:
        code = main()
    except SystemExit as exc:
        code = exc.code
        if code is None:
            code = 0
        elif not isinstance(code, int):         # sys.exit("message"): the message, status 1
            print(code, file=sys.stderr)
            code = 1
    leave(code)
