"""``report.png`` drawn by a second Python process while the fit runs.

Matplotlib takes ~0.4 s to import and ~0.3 s to draw the report, all of it
holding the GIL: imported on a thread beside the fit it slowed the fit's own
Python and NumPy work (the scene set-up 0.15 -> 0.4 s), and drawn after the fit
it is on the critical path. ``fitter fit`` therefore starts ``ReportProcess``
before importing JAX: the helper imports matplotlib and ``fitter.report`` and
loads the fonts on the other core, then waits for the outcome on its stdin
(pickled), draws it with the same ``fitter.report.build_report`` and answers
the PNG's bytes on its stdout (the page's axes are made before the outcome
arrives, ``fitter.report.new_figure``). The parent writes the file itself (the helper
touches no file). Any failure of the helper -- it did not start, died, or
answered something that is not a PNG -- returns None, and the caller draws
in-process (``fitter.outputs.write_outcome``), so the report never depends on it.

With validation the helper also scores the Mitsuba re-render (``compare``,
``fitter.metrics.compare``): colour-science imports matplotlib's pyplot and
3-D toolkit with it, ~1.0 s of the quickstart's 3.9 s validated run when
imported in the parent after the fit; the helper imports it while the fit
runs. A failed or silent helper returns None and the caller scores in-process.
"""

from __future__ import annotations

import io
import os
import pickle
import subprocess
import sys

_PNG = b"\x89PNG\r\n\x1a\n"


class ReportProcess:
    """A started helper (``serve``): ``compare`` a validation (``metrics``: its
    colour-science imported ahead), ``send`` an outcome, then ``receive`` its
    PNG; ``close`` stops it (unused, or after an error)."""

    def __init__(self, metrics: bool = False):
        root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env = dict(os.environ)
        env["PYTHONPATH"] = os.pathsep.join([root] + [p for p in env.get("PYTHONPATH", "")
                                                      .split(os.pathsep) if p])
        self.proc = subprocess.Popen(
            [sys.executable, "-c",
             f"from fitter.report_process import serve; serve(metrics={bool(metrics)})"],
            stdin=subprocess.PIPE, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env,
            start_new_session=True)  # a terminal's Ctrl-C goes to the parent, which stops it
        self._talk, self._png = None, None

    def compare(self, target, image, mask, timeout: float = 60.0) -> dict | None:
        """``fitter.metrics.compare(target, image, mask=mask)`` computed by the
        helper (one started without ``metrics`` imports colour-science now), or
        None (already drawing, failed, or silent for ``timeout`` s: then
        stopped, and the caller scores)."""
        import threading

        if self._talk is not None or self.proc.poll() is not None:
            return None
        box: list = []

        def ask():
            try:
                pickle.dump(("compare", target, image, mask), self.proc.stdin,
                            protocol=pickle.HIGHEST_PROTOCOL)
                self.proc.stdin.flush()
                box.append(pickle.load(self.proc.stdout))
            except Exception:  # noqa: BLE001 (broken pipe, garbage: scored in-process)
                pass

        asker = threading.Thread(target=ask, name="fitter-metrics", daemon=True)
        asker.start()
        asker.join(timeout)
        if not box or not isinstance(box[0], dict):
            self.close()  # its pipes are in an unknown state
            return None
        return box[0]

    def send(self, outcome, title: str, timeout: float = 120.0) -> None:
        """Start drawing ``outcome`` (``fitter.pipeline.Outcome``) titled ``title``.

        A thread feeds the pickle and collects the answer (the helper may still
        be importing, and the caller writes its other files meanwhile); a
        helper silent for ``timeout`` s is killed."""
        import threading

        try:
            data = pickle.dumps(("report", outcome, title), protocol=pickle.HIGHEST_PROTOCOL)
        except Exception:  # noqa: BLE001 (something unpicklable: receive() returns None)
            return

        def talk():
            try:
                png, _ = self.proc.communicate(data, timeout=timeout)
            except Exception:  # noqa: BLE001 (broken pipe, timeout: receive() returns None)
                return
            if self.proc.returncode == 0 and png.startswith(_PNG):
                self._png = png

        self._talk = threading.Thread(target=talk, name="fitter-report", daemon=True)
        self._talk.start()

    def receive(self) -> bytes | None:
        """The PNG's bytes, or None (not sent, or the helper failed)."""
        if self._talk is not None:
            self._talk.join()
        self.close()
        return self._png

    def close(self) -> None:
        """Stop the helper if it still runs (it was started by this object)."""
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        for pipe in (self.proc.stdin, self.proc.stdout):
            if pipe and not pipe.closed:
                try:
                    pipe.close()
                except OSError:
                    pass


def start(metrics: bool = False) -> ReportProcess | None:
    """A ``ReportProcess`` (that also scores validations: ``metrics``), or None
    where one cannot be started."""
    try:
        return ReportProcess(metrics)
    except Exception:  # noqa: BLE001 (no interpreter to start, no fork: draw in-process)
        return None


def serve(metrics: bool = False) -> None:
    """The helper's side: warm up (and import ``fitter.metrics``' colour-science),
    then answer requests on stdin, one pickle each: ("compare", target, image,
    mask) with the pickled scores (or None on an error) on stdout, and
    ("report", outcome, title) with the PNG's bytes, the last request."""
    import signal

    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the parent decides when to stop
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from . import report
    from . import config, pipeline  # noqa: F401 (imported while waiting: the outcome's classes)
    from .fit import result  # noqa: F401

    warm = Figure(figsize=(1, 1), dpi=100)  # font cache, glyphs and the Agg renderer
    FigureCanvasAgg(warm)
    warm.text(0.5, 0.5, "0.1 ± 2e-3 |", family="monospace")
    warm.text(0.5, 0.5, "CONVERGED ΔE", fontweight="bold")
    warm.canvas.draw()
    page = report.new_figure()  # the empty page and its axes, before the fit ends
    if metrics:
        from .metrics import warm_up

        warm_up()
    while True:
        request = pickle.load(sys.stdin.buffer)
        if request[0] == "report":
            break
        try:
            from .metrics import compare

            scores = compare(*request[1:3], mask=request[3])
        except Exception:  # noqa: BLE001 (the parent scores in-process and reports it)
            scores = None
        pickle.dump(scores, sys.stdout.buffer, protocol=pickle.HIGHEST_PROTOCOL)
        sys.stdout.buffer.flush()
    _, outcome, title = request
    buf = io.BytesIO()
    report.build_report(outcome, title, page=page).savefig(buf, format="png")
    sys.stdout.buffer.write(buf.getvalue())
    sys.stdout.buffer.flush()
    os._exit(0)  # the parent waits for the end of the stream: skip the interpreter's teardown
