"""Progress display: one `tqdm.auto` bar per run (a widget in Jupyter when ipywidgets is
installed, text on stderr in a terminal)."""

from __future__ import annotations

import contextlib
import signal
import sys
import threading

PROGRESS_CHOICES = "False, True, 'auto' or a tqdm bar"


def interactive() -> bool:
    """True in a terminal (stderr is a TTY) or inside a Jupyter kernel."""
    in_kernel = "ipykernel" in sys.modules
    return in_kernel or bool(getattr(sys.stderr, "isatty", lambda: False)())


def is_bar(progress) -> bool:
    return all(hasattr(progress, name) for name in ("update", "close", "set_postfix_str"))


def _is_auto(progress) -> bool:
    return isinstance(progress, str) and progress == "auto"


def check_progress(progress) -> None:
    """Refuse a `progress` argument that is none of the accepted kinds."""
    if progress is None or isinstance(progress, bool) or _is_auto(progress) or is_bar(progress):
        return
    raise TypeError(f"`progress` must be {PROGRESS_CHOICES}; got {progress!r}.")


def open_bar(progress, total: int | None, desc: str, unit: str = "step"):
    """(bar, owned): a new bar for `progress` True or "auto" (shown only when `interactive()`),
    the caller's bar itself (not owned: several calls advance one bar), or (None, False).
    The owner closes it with `close_bar`."""
    check_progress(progress)
    if is_bar(progress):
        return progress, False
    if not progress or (_is_auto(progress) and not interactive()):
        return None, False
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, file=sys.stderr, dynamic_ncols=True), True


def close_bar(bar, owned: bool) -> None:
    if bar is not None and owned:
        bar.close()


# Ctrl-C between iterations. Python runs a SIGINT handler in whatever frame is executing; a
# KeyboardInterrupt raised inside a garbage-collector callback (JAX registers one) is printed
# and dropped, and the run went on (seen in `jaxgeom tune`). Under `deferred_interrupt` the
# first Ctrl-C only sets a flag that the host loops read between iterations
# (`raise_if_interrupted`); a second one interrupts at once, as usual.
_INTERRUPT = {"requested": False}


@contextlib.contextmanager
def deferred_interrupt():
    """Within: Ctrl-C stops the run at the next iteration boundary (the CLI's commands).
    Outside the main thread (signal handlers cannot be set there) Ctrl-C acts as usual."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.getsignal(signal.SIGINT)

    def handler(signum, frame):
        if _INTERRUPT["requested"]:  # the second Ctrl-C: at once
            signal.signal(signal.SIGINT, previous)
            raise KeyboardInterrupt
        _INTERRUPT["requested"] = True

    _INTERRUPT["requested"] = False
    signal.signal(signal.SIGINT, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _INTERRUPT["requested"] = False


def raise_if_interrupted() -> None:
    """KeyboardInterrupt here if a deferred Ctrl-C is pending (once)."""
    if take_interrupt():
        raise KeyboardInterrupt


def take_interrupt() -> bool:
    """Whether a deferred Ctrl-C is pending; it is then consumed."""
    pending, _INTERRUPT["requested"] = _INTERRUPT["requested"], False
    return pending
