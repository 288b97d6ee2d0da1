"""The files of a fit's output folder: images, result.json, config.toml, report, scene.xml.

``write_outcome`` writes them into a staged folder (``fitter.outdir``); the
names are ``fitter.outdir.OUTPUT_NAMES``. Used by ``fitter fit`` and by each
job of ``fitter batch``.
"""

from __future__ import annotations

import json
import os
import sys

def _write_json(path: str, data) -> None:
    with open(path, "w", encoding="utf-8") as fh:
        json.dump(data, fh, indent=2, allow_nan=False)
        fh.write("\n")


def write_outcome(folder: str, outcome, result: dict, report=None) -> None:
    """Write an outcome's files into ``folder`` (a staged, still hidden folder).

    ``report``: a started ``fitter.report_process.ReportProcess`` that draws
    report.png while the other files are written; without one, or if it fails,
    the report is drawn here.
    """
    from .config import dumps_toml, job_to_dict
    from .imageio import write_image

    job = outcome.job
    title = f"{job.name}: {' + '.join(job.material.lobes)}"
    if report is not None:
        report.send(outcome, title)
    write_image(os.path.join(folder, "fit.exr"), outcome.rendered)
    write_image(os.path.join(folder, "residual.exr"), outcome.residual)
    if outcome.validation is not None:
        write_image(os.path.join(folder, "validation.exr"), outcome.validation.image)
    _write_json(os.path.join(folder, "result.json"), result)
    with open(os.path.join(folder, "config.toml"), "w", encoding="utf-8") as fh:
        fh.write(dumps_toml(job_to_dict(job)))
    from .mitsuba.export import export_job, MitsubaError

    try:  # scene.xml: the fit as a Mitsuba 3 scene
        export_job(folder, job, outcome.fit.params)
    except MitsubaError as exc:  # a material Mitsuba cannot express: the fit still counts
        print(f"warning: no scene.xml: {exc}", file=sys.stderr)
    png = report.receive() if report is not None else None
    if png is None:
        from .report import make_report

        make_report(os.path.join(folder, "report.png"), outcome, title=title)
    else:
        with open(os.path.join(folder, "report.png"), "wb") as fh:
            fh.write(png)
