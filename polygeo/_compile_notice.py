"""Say once on stderr that numba compiles the kernels (a cold cache), and only then.

The first run in a new environment (or after an upgrade) compiles the package's kernels,
15-40 s during which nothing else is printed. :func:`compile_notice` (re-exported by
:mod:`polygeo.cli`, whose ``main`` calls it for every sub-command unless ``--quiet``) registers
a listener for numba's ``numba:compile`` event. numba fires that event only when it compiles a
kernel, never when it loads one from its disk cache, so a warm run hears nothing and pays
nothing.

This lives apart from :mod:`polygeo.cli` because :mod:`polygeo._numba_cache` keys the kernel
cache on every source file that mentions numba: a module that does is a kernel source, and
editing the command line must not make every cached kernel stale.
"""

from __future__ import annotations

import sys

__all__ = ["COMPILE_NOTICE", "compile_notice"]

#: What :func:`compile_notice` writes (once) when a kernel is compiled instead of loaded.
COMPILE_NOTICE = ("polygeo: compiling kernels (first run only, ~30 s; cached on disk "
                  "afterwards)...")


def _said_once(stream_holder: dict, event) -> None:
    """Write the notice on the first start of a disk-cached kernel's compilation."""
    if stream_holder["said"] or not event.is_start:
        return
    dispatcher = (event.data or {}).get("dispatcher")
    cache = getattr(dispatcher, "_cache", None)
    if cache is None or type(cache).__name__ == "NullCache":  # compiled on every run anyway
        return
    stream_holder["said"] = True
    stream = stream_holder["stream"] if stream_holder["stream"] is not None else sys.stderr
    print(COMPILE_NOTICE, file=stream, flush=True)


#: State of the listener registered by :func:`compile_notice` (None: not registered).
_NOTICE: dict | None = None


def compile_notice(stream=None) -> bool:
    """Say once, when it starts, that numba is compiling kernels (a cold cache); idempotent.

    The first run in a new environment (or after an upgrade) compiles the package's kernels,
    15-40 s during which nothing else is printed. This registers a listener for numba's
    ``numba:compile`` event that writes :data:`COMPILE_NOTICE` the first time a kernel with
    a disk cache is compiled. numba fires that event only when it compiles, never when it
    loads a kernel from its disk cache, so warm runs print nothing and cost nothing; kernels
    without a disk cache (compiled on every run, in numba itself or in other packages) are
    ignored. :func:`main` calls it for every sub-command unless its ``--quiet`` is given.

    Parameters
    ----------
    stream : file-like, optional
        Where to write (default: ``sys.stderr`` at the time of writing).

    Returns
    -------
    bool
        True when the listener was registered by this call, False when it already was (its
        stream is then replaced) or numba is not installed.
    """
    global _NOTICE
    if _NOTICE is not None:
        _NOTICE["stream"] = stream
        return False
    try:
        from numba.core import event
    except ImportError:  # pragma: no cover - numba is a dependency
        return False

    class _Listener(event.Listener):
        def on_start(self, ev) -> None:
            _said_once(state, ev)

        def on_end(self, ev) -> None:
            pass

    state = {"stream": stream, "said": False}
    event.register("numba:compile", _Listener())
    _NOTICE = state
    return True
