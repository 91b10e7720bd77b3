"""Progress lines and messages of the diagnosis in words (``docs/diagnosis.md``, "Progress").

The diagnosis reports one line per step of the pipeline (the nominal estimate, the noise floor,
where, the numerical checks, the ranking, the confirmations) and one line per fit (what was fitted,
its result, its time): :func:`fit_line`.  A solver's message can run to several sentences (what
failed, where, and what to try); a line and ``report.md`` carry its first sentence
(:func:`brief`), ``diagnosis.json`` the whole text.  :func:`progress_sink` chooses where the lines
go: the caller's ``log``, else standard error; ``verbose`` adds every Newton iteration.
"""
from __future__ import annotations

import contextlib
import io
import math
import re
import sys
from typing import Callable, Iterator

__all__ = ["brief", "fit_line", "progress_sink", "LineWriter"]

#: where a message's first sentence ends: "; " or ". " (not the ". " of "e.g. " or "i.e. ")
_BOUNDARY = re.compile(r";\s|(?<!\be\.g)(?<!\bi\.e)\.\s")
_CLOSING = {"(": ")", "[": "]"}


def brief(message: str) -> str:
    """The first sentence of ``message`` (up to its first ``"; "`` or ``". "``, whole words), the
    brackets it leaves open closed with ``…)``; the message itself when it is one sentence."""
    text = " ".join(str(message).split())
    cut = _BOUNDARY.search(text)
    if cut is None:
        return text
    head = text[:cut.start()].rstrip(" ,:")
    stack = []
    for ch in head:
        if ch in _CLOSING:
            stack.append(_CLOSING[ch])
        elif stack and ch == stack[-1]:
            stack.pop()
    return head + (" …" + "".join(reversed(stack)) if stack else "")


def fit_line(what: str, res, seconds: float) -> str:
    """One line for a fit: ``what``, its J and iterations, or ``not converged: <first sentence of
    the solver's message>``, and its time; a converged fit whose message does not begin with
    "converged" (a fallback: the weight-continuation estimator's after a warm start stopped) adds
    that message's first sentence."""
    if res is None:
        return f"{what}: not evaluated, {seconds:.1f} s"
    if not res.success:
        return f"{what}: not converged: {brief(res.message)}, {seconds:.1f} s"
    J = f"J = {res.J:.5g}" if math.isfinite(res.J) else "J not finite"
    how = "" if str(res.message).startswith("converged") else f"; {brief(res.message)}"
    return f"{what}: {J}, {res.iterations} iterations, {seconds:.1f} s{how}"


class LineWriter(io.TextIOBase):
    """A text stream that hands each complete line written to it to ``say`` (what the estimator
    prints in verbose mode, sent where the diagnosis's progress lines go)."""

    def __init__(self, say: Callable[[str], None]):
        super().__init__()
        self.say, self._part = say, ""

    def writable(self) -> bool:
        return True

    def write(self, s: str) -> int:
        lines = (self._part + s).split("\n")
        self._part = lines.pop()
        for line in lines:
            self.say(line)
        return len(s)

    def flush(self) -> None:
        if self._part:
            self.say(self._part)
            self._part = ""


@contextlib.contextmanager
def progress_sink(log: Callable[[str], None] | None, progress: bool,
                  verbose: bool) -> Iterator[Callable[[str], None] | None]:
    """The function the progress lines are given to: ``log`` if given, else (with ``progress``) a
    line on standard error, else None (no lines).  With ``verbose`` and no ``log``, what the
    estimators print (a line per Newton iteration) is sent to standard error as well while the
    context lasts; with a ``log`` it stays on standard output."""
    if log is not None:
        yield log
        return
    if not progress:
        yield None
        return
    err = sys.stderr

    def say(line: str) -> None:
        print(line, file=err, flush=True)
    if not verbose:
        yield say
        return
    writer = LineWriter(say)
    with contextlib.redirect_stdout(writer):
        try:
            yield say
        finally:
            writer.flush()
