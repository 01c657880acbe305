"""Wrappers of the CASA tasks the recipes use: fringefit, gaincal, applycal, imfit.

Each wrapper runs the task through :func:`hitops.casa.runner.run_task` (which
fails on SEVERE log lines), then checks that the output it promises exists,
and returns a dict of plain Python values that Stimela's ``python`` flavour
maps onto the cab's outputs.
"""

from __future__ import annotations

import json
import logging
import math
import shutil
from contextlib import contextmanager
from pathlib import Path
from typing import Dict, List, Optional, Sequence, Union

import numpy as np

from ..errors import ExternalToolError, InputError, MeasurementSetError, OutputExistsError
from ..io import flag_versions
from .runner import run_task

log = logging.getLogger("hitops.casa")

StrList = Union[str, Sequence[str], None]


def _as_list(value: StrList) -> List[str]:
    """Stimela passes lists; the CLI and users may pass 'a,b'."""
    if value is None or value == "":
        return []
    if isinstance(value, str):
        return [v.strip() for v in value.split(",") if v.strip()]
    return [str(v) for v in value]


def _parent(path: str) -> str:
    """The directory of a step's output: its CASA log goes there (hitops.casa.runner.log_path)."""
    return str(Path(path).resolve().parent)


def _check_ms(vis: str) -> None:
    if not (Path(vis) / "table.dat").exists():
        raise MeasurementSetError(f"'{vis}' is not a Measurement Set (no table.dat); "
                                  "check the path or run the simulate step first")


def _prepare_output(path: str, overwrite: bool) -> None:
    """Remove an old output only when asked to, so a rerun never mixes tables."""
    target = Path(path)
    if target.exists():
        if not overwrite:
            raise OutputExistsError(f"calibration table '{path}' exists; pass overwrite=True "
                                    "(cab: overwrite=true) to replace it")
        shutil.rmtree(target)


@contextmanager
def _no_table_on_failure(caltable: str):
    """Remove a (partial) table when the solve fails, so that a pipeline rerun
    does not mistake it for a finished result and skip the step."""
    try:
        yield
    except BaseException:
        if Path(caltable).exists():
            log.warning("removing %s left by the failed solve", caltable)
            shutil.rmtree(caltable, ignore_errors=True)
        raise


def table_summary(caltable: str, task: str) -> Dict[str, float]:
    """Rows and flagged fraction of a calibration table; raise if none was written.

    CASA's solvers log "Insufficient unflagged antennas" for every interval and
    then write no table (or an empty one) without raising: that must fail the step.
    """
    from casacore import tables as pt

    path = Path(caltable)
    if not (path / "table.dat").exists():
        raise ExternalToolError(f"CASA {task} wrote no calibration table at '{caltable}' "
                                "(no output calibration table written); check the refant "
                                "list, the SNR threshold and the flags")
    with pt.table(str(path), ack=False) as tab:
        n_rows = tab.nrows()
        if n_rows == 0:
            raise ExternalToolError(f"CASA {task} wrote an empty calibration table "
                                    f"'{caltable}': no interval had a solution")
        flags = tab.getcol("FLAG")
    flagged = float(np.mean(flags)) if flags.size else 1.0
    if flagged >= 1.0:
        raise ExternalToolError(f"every solution in '{caltable}' ({task}) is flagged; "
                                "lower minsnr, lengthen solint or check the data")
    log.info("%s: %d rows, %.1f%% of solutions flagged", caltable, n_rows, 100 * flagged)
    return {"n_rows": int(n_rows), "flagged_fraction": flagged}


def fringefit(vis: str, caltable: str, solint: str = "20s", refant: StrList = "",
              minsnr: float = 3.0, field: str = "", spw: str = "",
              zerorates: bool = False, globalsolve: bool = True,
              gaintable: StrList = None, overwrite: bool = False,
              restore_flags: StrList = "") -> Dict[str, object]:
    """CASA fringefit: delay/rate/phase solutions per ``solint``.

    ``refant`` should be a priority list (e.g. "PV,PB,AP"): CASA stops with
    "No valid reference antenna supplied" when a single refant sets mid-track.
    ``restore_flags``: flag versions whose union becomes FLAG before the solve.
    """
    _check_ms(vis)
    _prepare_output(caltable, overwrite)
    _restore_flags(vis, restore_flags)
    refants = _as_list(refant)
    with _no_table_on_failure(caltable):
        run_task("fringefit", log_dir=_parent(caltable), vis=vis, caltable=caltable,
                 field=field, spw=spw,
                 solint=solint, refant=",".join(refants), minsnr=float(minsnr),
                 zerorates=bool(zerorates), globalsolve=bool(globalsolve),
                 gaintable=_as_list(gaintable))
        summary = table_summary(caltable, "fringefit")
    return {"caltable": caltable, **summary}


def gaincal(vis: str, caltable: str, solint: str = "10s", refant: StrList = "",
            calmode: str = "p", gaintype: str = "G", minsnr: float = 3.0,
            field: str = "", spw: str = "", gaintable: StrList = None,
            minblperant: int = 4, overwrite: bool = False,
            restore_flags: StrList = "") -> Dict[str, object]:
    """CASA gaincal (self-calibration against the model, default a 1 Jy point source).

    ``minblperant`` (CASA default 4) must be at most n_ant - 1: with four
    stations every interval fails with "Insufficient unflagged antennas".
    ``restore_flags``: flag versions whose union becomes FLAG before the solve.
    """
    _check_ms(vis)
    if calmode not in ("p", "a", "ap"):
        raise InputError(f"gaincal calmode '{calmode}' must be one of p, a, ap")
    _prepare_output(caltable, overwrite)
    _restore_flags(vis, restore_flags)
    with _no_table_on_failure(caltable):
        run_task("gaincal", log_dir=_parent(caltable), vis=vis, caltable=caltable,
                 field=field, spw=spw,
                 solint=solint, refant=",".join(_as_list(refant)), calmode=calmode,
                 gaintype=gaintype, minsnr=float(minsnr), gaintable=_as_list(gaintable),
                 minblperant=int(minblperant))
        summary = table_summary(caltable, "gaincal")
    return {"caltable": caltable, **summary}


def applycal(vis: str, gaintable: StrList, interp: StrList = None,
             applymode: str = "calflag", calwt: bool = False,
             flagbackup: bool = False, receipt: str | None = None,
             restore_flags: StrList = "", save_flags: str = "") -> Dict[str, object]:
    """CASA applycal into CORRECTED_DATA; check the column exists afterwards.

    Returns the fraction of the data flagged after the apply.  ``receipt``
    names a JSON file written on success: the MS is changed in place, so the
    receipt is the file a pipeline can test for "this step is done".
    ``restore_flags``: flag versions whose union becomes FLAG before the apply;
    ``save_flags``: the flag version the result is kept as (CASA's .flagversions).
    """
    from casacore import tables as pt

    _check_ms(vis)
    tables = _as_list(gaintable)
    if not tables:
        raise InputError("applycal needs at least one gaintable")
    for table in tables:
        if not (Path(table) / "table.dat").exists():
            raise InputError(f"applycal: calibration table '{table}' does not exist; "
                             "run the solve step first")
    _restore_flags(vis, restore_flags)
    run_task("applycal", log_dir=_parent(receipt or vis), vis=vis, gaintable=tables,
             interp=_as_list(interp),
             applymode=applymode, calwt=[bool(calwt)] * len(tables),
             flagbackup=bool(flagbackup))
    with pt.table(vis, ack=False) as tab:
        if "CORRECTED_DATA" not in tab.colnames():
            raise ExternalToolError(f"applycal left no CORRECTED_DATA column in '{vis}'")
        flags = tab.getcol("FLAG")
    flagged = float(np.mean(flags)) if flags.size else 1.0
    log.info("%s: CORRECTED_DATA written, %.1f%% flagged", vis, 100 * flagged)
    if save_flags:
        flag_versions.save_version(vis, save_flags, f"after CASA applycal of {', '.join(tables)} "
                                   f"(applymode {applymode}; started from "
                                   f"{', '.join(_as_list(restore_flags)) or 'FLAG'})")
    # only the cab's declared outputs are returned (Stimela rejects others)
    out = {"flagged_fraction": flagged}
    if receipt:
        _write_json(receipt, {"vis": vis, "gaintable": tables, "applymode": applymode,
                              "flagged_fraction": flagged})
        out["receipt"] = receipt
    return out


def _restore_flags(vis: str, versions: StrList) -> None:
    """FLAG set to the union of saved flag versions, so a step starts from declared
    flags and not from whatever an earlier step or run left (docs/recipes.md)."""
    names = _as_list(versions)
    if names:
        flag_versions.restore_versions(vis, names)


def _write_json(path: str, payload: Dict[str, object]) -> None:
    """Write atomically, so a half-written file never marks a step as done."""
    target = Path(path)
    target.parent.mkdir(parents=True, exist_ok=True)
    tmp = target.with_name(target.name + ".partial")
    tmp.write_text(json.dumps(payload, indent=2) + "\n")
    tmp.replace(target)


def _quantity(q) -> float:
    return float(np.asarray(q["value"]).ravel()[0])


def _image_shape_and_stats(imagename: str, box: str) -> Dict[str, object]:
    """Shape, brightest pixel and robust rms inside ``box`` (casatools image tool).

    ``max`` is NaN when the box holds no finite pixel (e.g. a CLEAN that
    diverged to NaN), which CASA imfit would abort on.
    """
    from ..casa_env import ensure_casa_offline

    ensure_casa_offline()
    import casatools

    ia = casatools.image()
    try:
        ia.open(str(imagename))
        shape = [int(n) for n in ia.shape()]
        rg = casatools.regionmanager()
        region = rg.box(blc=[int(v) for v in box.split(",")[:2]],
                        trc=[int(v) for v in box.split(",")[2:]]) if box else {}
        stats = ia.statistics(region=region, robust=True, verbose=False)
        rg.done()
    finally:
        ia.done()
    peak = np.asarray(stats.get("max", [])).ravel()
    if peak.size == 0 or not np.isfinite(peak[0]):
        return {"shape": shape, "max": float("nan"), "maxpos": [float("nan")] * 2,
                "rms": float("nan")}
    return {"shape": shape, "max": float(peak[0]),
            "maxpos": [float(v) for v in np.asarray(stats["maxpos"]).ravel()[:2]],
            "rms": float(np.asarray(stats["medabsdevmed"]).ravel()[0]) * 1.4826}


def centre_box(imagename: str, half_width: int) -> str:
    """CASA box string of +-half_width pixels around the image centre."""
    shape = _image_shape_and_stats(imagename, "")["shape"]
    cx, cy = shape[0] // 2, shape[1] // 2
    half = int(half_width)
    return f"{max(cx - half, 0)},{max(cy - half, 0)},{min(cx + half, shape[0] - 1)},{min(cy + half, shape[1] - 1)}"


#: WSClean's products of one image name that a diverged CLEAN leaves unusable
DIVERGED_PRODUCTS = ("image", "model", "residual")


def diverged_name(path: str | Path) -> Path:
    """Where a diverged CLEAN's product is kept: X-image.fits -> X-image.diverged.fits."""
    path = Path(path)
    return path.with_name(f"{path.stem}.diverged{path.suffix}")


def _wsclean_products(imagename: str | Path) -> List[Path]:
    """The restored, model and residual images of a WSClean name (X-image.fits -> X-*.fits)."""
    path = Path(imagename)
    if not path.name.endswith("-image.fits"):
        return [path]
    prefix = path.name[: -len("-image.fits")]
    return [path.with_name(f"{prefix}-{kind}.fits") for kind in DIVERGED_PRODUCTS]


def _conform_fits(*paths: Optional[str]) -> None:
    """Fix WSClean's non-conforming header cards before CASA reads the files."""
    from .fits import conform_header

    for path in paths:
        if path and str(path).endswith(".fits"):
            for sibling in _wsclean_products(path) + [Path(path)]:
                changed = conform_header(sibling)
                if changed:
                    log.debug("%s: header cards %s rewritten in FITS fixed format",
                              sibling, ",".join(changed))


def _box_contains(box: str, x: float, y: float) -> bool:
    if not box:
        return True
    blcx, blcy, trcx, trcy = (float(v) for v in box.split(","))
    return blcx <= x <= trcx and blcy <= y <= trcy


def imfit(imagename: str, box: str = "", region: str = "", stokes: str = "I",
          centre_half_width: int = 0, fallback: bool = False,
          fallback_image: Optional[str] = None, max_abs_peak: float = 0.0,
          detection_snr: float = 0.0, mark_diverged: bool = False,
          label: str = "", outfile: Optional[str] = None) -> Dict[str, object]:
    """Fit one 2-D Gaussian with CASA imfit; return its peak and error (Jy/beam).

    Also returns the integrated flux and its error and the fitted centre
    (pixels), all plain floats.  ``centre_half_width`` > 0 restricts the fit
    to a box of that many pixels around the image centre (the phase centre,
    where the simulated source sits), which keeps imfit off sidelobes and fast.

    * **No source**: with ``detection_snr`` > 0, a fit whose peak is below
      ``detection_snr`` times the image's robust rms, or whose centre lies
      outside the box, is not a measurement: the result is ``method:
      no-source`` with no peak (the JSON keeps the fitted value, the rms and
      the ratio under ``brightest``, ``rms`` and ``snr``).  Raw data with the
      troposphere left in image to noise, and a Gaussian fitted to that noise
      is not a peak flux.
    * **CLEAN diverged**: a fit that does not converge, or whose |peak| exceeds
      ``max_abs_peak`` (> 0; CLEAN can diverge on incoherent data with sparse
      VLBI coverage and restore a peak of 1e20 Jy), fails the step, unless
      ``fallback`` is set: then the brightest pixel in the box of
      ``fallback_image`` (e.g. the dirty image, which needs no deconvolution)
      or of the image itself is reported with the robust rms as its error,
      marked ``method: max-pixel``.  With ``mark_diverged`` a diverged
      WSClean image X-image.fits (and X-model, X-residual) is renamed
      X-image.diverged.fits, so that only usable images keep the usual names;
      the dirty image stays where it is and the JSON names it.

    ``outfile`` (JSON) keeps the result with its ``label`` (e.g. "pwc") for the
    peak-flux comparison, which reads files so that it still works when this
    step is skipped on a rerun.  WSClean's FITS headers are first rewritten in
    the FITS fixed format where they are not (:mod:`hitops.casa.fits`).
    """
    log_dir = _parent(outfile or imagename)
    marked = diverged_name(imagename)
    earlier = None
    if not Path(imagename).exists():
        if not (fallback and marked.exists()):
            raise InputError(f"imfit: image '{imagename}' does not exist; run the imaging step first")
        # an earlier run found this CLEAN diverged and renamed the image
        earlier = f"CLEAN diverged (the restored image was renamed {marked} by an earlier run)"
    _conform_fits(imagename, fallback_image)
    if centre_half_width and not box:
        box = centre_box(fallback_image if earlier else imagename, centre_half_width)
    error = earlier
    diverged = earlier is not None
    stats = None
    if error is None:
        try:
            # CASA imfit aborts the whole process (C++ ArrayError) on an image without
            # finite pixels, so look first
            stats = _image_shape_and_stats(imagename, "")
            if not math.isfinite(_image_shape_and_stats(imagename, box)["max"]):
                diverged = True
                raise ExternalToolError(f"'{imagename}' has no finite pixel in box '{box}' "
                                        "(the deconvolution produced NaN)")
            result = run_task("imfit", log_dir=log_dir, imagename=str(imagename), box=box,
                              region=region, stokes=stokes)
            if not result or not result.get("converged", [False])[0]:
                raise ExternalToolError(f"imfit did not converge on '{imagename}'")
        except ExternalToolError as err:
            if not fallback:
                raise
            error = err
    if error is None:
        comp = result["results"]["component0"]
        peak = comp["peak"]
        flux = comp["flux"]
        pixel = comp.get("pixelcoords", np.array([np.nan, np.nan]))
        out = {
            "method": "gaussian",
            "peak": _quantity(peak),
            # peak["error"] is a bare float in casatasks 6.7, a quantity in some versions
            "peak_err": _quantity(peak["error"]) if isinstance(peak["error"], dict)
            else float(np.asarray(peak["error"]).ravel()[0]),
            "flux": float(np.asarray(flux["value"]).ravel()[0]),
            "flux_err": float(np.asarray(flux["error"]).ravel()[0]),
            "x_pix": float(pixel[0]),
            "y_pix": float(pixel[1]),
        }
        bad = None
        if not all(math.isfinite(out[k]) for k in ("peak", "peak_err")):
            bad = f"imfit on '{imagename}' returned a non-finite peak"
        elif max_abs_peak and abs(out["peak"]) > max_abs_peak:
            bad = (f"imfit peak {out['peak']:.3g} Jy/beam on '{imagename}' exceeds "
                   f"{max_abs_peak:g} Jy/beam: the deconvolution diverged")
        if bad:
            if not fallback:
                raise ExternalToolError(bad)
            error = bad
            diverged = True
    extra: Dict[str, object] = {}
    if error is None and detection_snr > 0:
        rms = stats["rms"] if stats else float("nan")
        snr = out["peak"] / rms if rms > 0 else float("inf")
        inside = _box_contains(box, out["x_pix"], out["y_pix"])
        if snr < detection_snr or not inside:
            why = (f"the fitted peak {out['peak']:.4f} Jy/beam is {snr:.1f} x the image rms "
                   f"{rms:.4f} Jy/beam (< {detection_snr:g})" if snr < detection_snr else
                   f"the fitted centre ({out['x_pix']:.0f}, {out['y_pix']:.0f}) lies outside "
                   f"the fit box {box}")
            log.warning("no source in %s: %s", imagename, why)
            extra = {"brightest": out["peak"], "brightest_err": out["peak_err"], "rms": rms,
                     "snr": snr, "x_pix": out["x_pix"], "y_pix": out["y_pix"],
                     "reason": f"no source: {why}"}
            out = {"method": "no-source", "peak": None, "peak_err": None}
        else:
            extra = {"rms": rms, "snr": snr}
    if (error is not None and not diverged and detection_snr > 0 and stats
            and stats["rms"] > 0):
        # the fit did not converge on a finite image: a source would have been fitted
        inbox = _image_shape_and_stats(imagename, box)
        snr = inbox["max"] / stats["rms"]
        if snr < detection_snr:
            why = (f"imfit did not converge and the brightest pixel in the box, "
                   f"{inbox['max']:.4f} Jy/beam, is {snr:.1f} x the image rms "
                   f"{stats['rms']:.4f} Jy/beam (< {detection_snr:g})")
            log.warning("no source in %s: %s", imagename, why)
            extra = {"brightest": inbox["max"], "rms": stats["rms"], "snr": snr,
                     "x_pix": inbox["maxpos"][0], "y_pix": inbox["maxpos"][1],
                     "reason": f"no source: {why}"}
            out = {"method": "no-source", "peak": None, "peak_err": None}
            error = None
    if error is not None:
        source = fallback_image or imagename
        if not Path(source).exists():
            raise InputError(f"imfit fallback image '{source}' does not exist")
        log.warning("%s; reporting the brightest pixel of %s instead (fallback)", error, source)
        stats = _image_shape_and_stats(source, box)
        if not math.isfinite(stats["max"]):
            raise ExternalToolError(f"{error}; the fallback image '{source}' has no finite "
                                    "pixel either")
        # no flux/flux_err: they are undefined without a fit (and NaN is not JSON)
        out = {"method": "max-pixel", "peak": stats["max"], "peak_err": stats["rms"],
               "x_pix": stats["maxpos"][0], "y_pix": stats["maxpos"][1]}
        extra = {"fallback_image": str(source), "reason": str(error), "diverged": diverged}
        if diverged and mark_diverged and earlier is None:
            extra["renamed"] = _mark_diverged(imagename)
        elif earlier is not None:
            extra["renamed"] = [str(diverged_name(p)) for p in _wsclean_products(imagename)
                                if diverged_name(p).exists()]
    elif mark_diverged:
        # a converged fit: images marked diverged by an earlier run are stale now
        for product in _wsclean_products(imagename):
            diverged_name(product).unlink(missing_ok=True)
    if out["peak"] is None:
        log.info("imfit %s: %s", imagename, extra["reason"])
    else:
        log.info("imfit %s: peak %.5f +- %.5f Jy/beam (%s)", imagename, out["peak"],
                 out["peak_err"], out["method"])
    if outfile:
        _write_json(outfile, {"label": label or Path(imagename).stem, "image": str(imagename),
                              "box": box, **out, **extra})
    # Stimela's outputs: plain floats, and none for a value that does not exist
    ret = {k: v for k, v in out.items() if v is not None}
    if outfile:
        ret["outfile"] = outfile
    return ret


def _mark_diverged(imagename: str) -> List[str]:
    """Rename a diverged CLEAN's restored, model and residual images (X-*.diverged.fits)."""
    renamed = []
    for product in _wsclean_products(imagename):
        if product.exists():
            target = diverged_name(product)
            product.replace(target)
            renamed.append(str(target))
    if renamed:
        log.warning("CLEAN diverged: %s renamed %s; the dirty image is the one to look at",
                    imagename, ", ".join(Path(r).name for r in renamed))
    return renamed
