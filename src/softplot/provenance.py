"""What a result was made on: the scan (name, size, sha256) and the camera, checked on use.

A detection (``softplot detect`` / ``process`` JSON), a film correction and a session record
the scan they were measured on (:func:`softplot.io.fingerprint`) and the camera certificate's
name. :func:`check_detection` refuses to apply one to another scan or another camera, in one
line naming both; with ``force`` the mismatch is returned as a warning for the output
instead.
"""

from __future__ import annotations

from pathlib import Path

from softplot.errors import SoftplotError

__all__ = ["check_detection", "check_camera", "ProvenanceError"]


class ProvenanceError(SoftplotError):
    """A result applied to a scan or camera it was not made on."""


def _refuse_or_warn(msg: str, force: bool, warnings: list[str]) -> None:
    if not force:
        raise ProvenanceError(msg + " (use --force to apply it anyway)")
    warnings.append("warning: " + msg + "; applied anyway (--force)")


def check_camera(made_with: str | None, camera_name: str, what: str, *,
                 force: bool = False) -> list[str]:
    """Refuse ``what`` (made with camera ``made_with``) used with ``camera_name``.

    Returns the warnings to print (only with ``force``); a result that names no camera passes.
    """
    warnings: list[str] = []
    if made_with and str(made_with) != camera_name:
        _refuse_or_warn(f"{what} was measured with camera {made_with!r}, not {camera_name!r}",
                        force, warnings)
    return warnings


def check_detection(det: dict, *, camera_name: str, scan_path: str | Path | None = None,
                    scan_size: tuple[int, int] | None = None, force: bool = False) -> list[str]:
    """Refuse a detection dict used with another camera or on another scan.

    The scan is compared by its recorded fingerprint (``det["scan"]``: size in bytes, then
    sha256) when the detection has one; otherwise by the image name and its size in px
    (``scan_size`` = (width, height)). Raises :class:`ProvenanceError` (one line naming both);
    with ``force`` returns the mismatches as warnings instead.
    """
    from softplot.io import check_fingerprint

    what = str(det.get("_source") or "the detection")
    warnings = check_camera(det.get("camera"), camera_name, what, force=force)
    if scan_path is None:
        return warnings
    sp = Path(scan_path)
    rec = det.get("scan")
    if isinstance(rec, dict) and rec.get("sha256"):
        try:
            check_fingerprint(sp, rec, what=what)
        except SoftplotError as exc:
            _refuse_or_warn(str(exc), force, warnings)
        return warnings
    image = det.get("image")
    if image and Path(str(image)).name != sp.name:
        _refuse_or_warn(f"{what} was made on {Path(str(image)).name}, not on {sp.name}",
                        force, warnings)
    w, h = det.get("width"), det.get("height")
    if scan_size is not None and w and h and (int(w), int(h)) != tuple(scan_size):
        _refuse_or_warn(f"{what} was made on a {w} x {h} px scan; {sp.name} is "
                        f"{scan_size[0]} x {scan_size[1]} px", force, warnings)
    return warnings
