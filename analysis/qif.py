"""QIF 3.0 results documents (ANSI/DMSC QIF 3.0, ISO 23952): what quality systems read.

:func:`inspection_document` writes an inspection's regions as surface-profile characteristics
of "other surface" features; :func:`acceptance_document` writes VDI/VDE 2634 figures as
measured characteristics with their MPEs. Both build an lxml tree in the namespace
``http://qifstandards.org/xsd/qif3`` following the element order of the official XSDs.
:func:`validate` checks a document against those XSDs (lxml), from a folder laid out as the
standard lays them out (``QIFApplications/``, ``QIFLibrary/``); the one network import (W3C
XML Signature) is resolved to the copy the ``signxml`` package ships.

A result that QIF cannot hold (no regions, a non-finite value, a unit QIF has no name for) is
refused with QIFError, never written half-valid. docs/reference/qif.md maps each scancell figure to its
QIF element.
"""

from __future__ import annotations

import datetime as dt
import math
import uuid
from collections.abc import Sequence
from dataclasses import dataclass, field
from decimal import Decimal
from pathlib import Path
from typing import Any

from lxml import etree
from scancell.analysis.decision import Zone, combine, decide

NS = "http://qifstandards.org/xsd/qif3"
QIF_VERSION = "3.0.0"
#: scancell's length unit names -> metres per unit (QIF's UnitConversion factor to SI)
LINEAR_UNITS = {"mm": 0.001, "cm": 0.01, "m": 1.0, "in": 0.0254}


#: QIF's ``DigitalModelFormatEnum`` values a nominal can have here
DIGITAL_MODEL_FORMATS = ("STEPAP203", "STEPAP203E2", "STEPAP214", "STEPAP242")
#: STEP ``FILE_SCHEMA`` names -> the QIF format (ISO 10303-21 header)
STEP_SCHEMAS = {"CONFIG_CONTROL_DESIGN": "STEPAP203", "AUTOMOTIVE_DESIGN": "STEPAP214",
                "AP203_CONFIGURATION_CONTROLLED_3D_DESIGN_OF_MECHANICAL_PARTS_AND_ASSEMBLY_MIM_LF":
                    "STEPAP203E2",
                "AP242_MANAGED_MODEL_BASED_3D_ENGINEERING_MIM_LF": "STEPAP242"}


def nominal_format(path: str | Path) -> str:
    """The QIF format name of a nominal file: the STEP application protocol its header's
    ``FILE_SCHEMA`` names, else the file's extension in capitals (``STL``, ``PLY``)."""
    p = Path(path)
    if p.suffix.lower() in (".step", ".stp"):
        try:
            head = p.read_bytes()[:4096].decode("latin-1").upper()
        except OSError:
            return "STEP"
        for name, fmt in STEP_SCHEMAS.items():
            if name in head:
                return fmt
        return "STEP"
    return p.suffix.lstrip(".").upper() or "unknown"


class QIFError(ValueError):
    """A result QIF cannot express, or a document the schemas refuse; the message says which."""


@dataclass(frozen=True)
class Region:
    """One toleranced region: its name, the points judged, the tolerance zone (mm, lower <
    upper, either may be None for one-sided), the deviations found and the verdict."""

    name: str
    points: int
    lower_mm: float | None
    upper_mm: float | None
    min_mm: float
    max_mm: float
    mean_mm: float
    passed: bool
    #: the decision rule's verdict (analysis/decision.py); "" where only ``passed`` is known
    verdict: str = ""
    #: the typical point's expanded uncertainty (mm, k = 2), where known
    u_mm: float | None = None


#: a verdict as QIF's CharacteristicStatusEnum and InspectionStatusEnum say it
CHARACTERISTIC_STATUS = {"pass": "PASS", "fail": "FAIL", "not provable": "INDETERMINATE",
                         "not measured": "NOT_ANALYZED"}
INSPECTION_STATUS = {"pass": "PASS", "fail": "FAIL", "not provable": "UNKNOWN",
                     "not measured": "NOT_MEASURED"}


@dataclass(frozen=True)
class AcceptanceFigure:
    """A VDI/VDE 2634 figure: its name (PF, PS, SD, ...), the measured value and the maximum
    permissible error (mm), and whether it passed."""

    name: str
    value_mm: float
    mpe_mm: float
    passed: bool
    description: str = ""


@dataclass
class Traceability:
    """Where a result came from: the job, the recording, the calibrations in force."""

    job_id: str | None = None
    recording: str | None = None
    calibration_ids: dict[str, str] = field(default_factory=dict)
    operator: str | None = None


class _Ids:
    def __init__(self) -> None:
        self.last = 0

    def __call__(self) -> str:
        self.last += 1
        return str(self.last)


def _q(tag: str) -> str:
    return f"{{{NS}}}{tag}"


def _el(parent: etree._Element | None, tag: str, text: Any = None, **attrs: Any
        ) -> etree._Element:
    e = (etree.Element(_q(tag), nsmap={None: NS}) if parent is None
         else etree.SubElement(parent, _q(tag)))
    for k, v in attrs.items():
        e.set(k, str(v))
    if text is not None:
        e.text = _text(text)
    return e


def _text(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float):
        if not math.isfinite(v):
            raise QIFError(f"a value of {v} cannot be written to QIF")
        # xs:decimal has no exponent: the shortest digits that read back exactly, positional
        return format(Decimal(repr(float(v))), "f")
    return str(v)


def _ids_list(parent: etree._Element, tag: str, ids: Sequence[str]) -> etree._Element:
    e = _el(parent, tag, n=len(ids))
    for i in ids:
        _el(e, "Id", i)
    return e


def _now() -> str:
    return dt.datetime.now(dt.UTC).replace(microsecond=0, tzinfo=None).isoformat()


def _root(ids: _Ids, application: str) -> etree._Element:
    root = _el(None, "QIFDocument", versionQIF=QIF_VERSION, idMax="0")
    _el(root, "QPId", str(uuid.uuid4()))
    _el(_el(root, "Version"), "TimeCreated", _now())
    _el(_el(_el(root, "Header"), "Application"), "Name", f"scancell {application}")
    return root


def _file_units(root: etree._Element, unit: str) -> None:
    if unit not in LINEAR_UNITS:
        raise QIFError(f"length unit {unit!r}: QIF results are written in one of "
                       f"{', '.join(LINEAR_UNITS)}")
    pu = _el(_el(root, "FileUnits"), "PrimaryUnits")
    lin = _el(pu, "LinearUnit")
    _el(lin, "SIUnitName", "meter")
    _el(lin, "UnitName", unit)
    _el(_el(lin, "UnitConversion"), "Factor", LINEAR_UNITS[unit])


def _standards(root: etree._Element, ids: _Ids, organization: str = "ISO",
               designator: str = "1101", year: str = "2017", title: str | None = None) -> str:
    """The standard the characteristics are read by (default ISO 1101, profile of a
    surface); an organization QIF does not list is ``OTHER`` with its name in the title."""
    defs = _el(root, "StandardsDefinitions", n=1)
    std_id = ids()
    std = _el(defs, "Standard", id=std_id)
    org = _el(std, "Organization")
    if organization in ("ASME", "ISO"):
        _el(org, "StandardsOrganizationEnum", organization)
    else:
        _el(org, "OtherStandardsOrganization", organization)
    _el(std, "Designator", designator)
    _el(std, "Year", year)
    if title:
        _el(std, "Title", title)
    return std_id


def _traceability(parent: etree._Element, tag: str, t: Traceability, std_id: str | None,
                  ids: _Ids) -> etree._Element:
    """Pre-inspection or inspection traceability: the job as the report number, the
    calibrations in force as notable events."""
    tr = _el(parent, tag)
    if t.job_id:
        _el(tr, "ReportNumber", t.job_id)
    _el(tr, "InspectionScope", "DETAIL")
    _el(tr, "InspectionMode", "100Percent")
    notes = [f"{k} calibration {v}" for k, v in sorted(t.calibration_ids.items())]
    if t.operator:
        notes.append(f"operator {t.operator}")
    if notes:
        ev = _el(tr, "NotableEvents", n=len(notes))
        for note in notes:
            e = _el(ev, "NotableEvent", id=ids())
            _el(e, "Description", note)
            _el(e, "Active", True)
    if std_id is not None:  # the pre-inspection traceability names the standard
        _el(tr, "FormalStandardId", std_id)
    return tr


def _device(root: etree._Element, ids: _Ids, name: str, description: str) -> str:
    devices = _el(_el(root, "MeasurementResources"), "MeasurementDevices", n=1)
    dev_id = ids()
    dev = _el(devices, "MeasurementDevice", id=dev_id)
    _el(dev, "Name", name)
    _el(dev, "Description", description)
    return dev_id


def _product(root: etree._Element, ids: _Ids, part_name: str, nominal_file: str | None,
             nominal_format: str | None) -> None:
    parts = _el(_el(root, "Product"), "PartSet", n=1)
    part = _el(parts, "Part", id=ids())
    _el(part, "ModelNumber", part_name)
    if nominal_file:
        ext = _el(part, "DefinitionExternal", id=ids(), n=1)
        model = _el(ext, "DigitalModel", id=ids())
        _el(model, "Name", Path(nominal_file).name)
        f = _el(model, "File")
        _el(f, "Name", nominal_file)
        fmt = _el(f, "Format")
        if nominal_format in DIGITAL_MODEL_FORMATS:
            _el(fmt, "DigitalModelFormatEnum", nominal_format)
        else:
            _el(fmt, "OtherDigitalModelFormat", nominal_format or "unknown")


def _characteristics(root: etree._Element, std_id: str, n: int
                     ) -> tuple[etree._Element, etree._Element, etree._Element]:
    """``Characteristics`` read by the standard ``std_id``: its definitions, nominals and
    items, ``n`` of each to come."""
    chars = _el(root, "Characteristics")
    _el(chars, "FormalStandardId", std_id)
    return (_el(chars, "CharacteristicDefinitions", n=n),
            _el(chars, "CharacteristicNominals", n=n), _el(chars, "CharacteristicItems", n=n))


def _finish(root: etree._Element, ids: _Ids) -> etree._ElementTree:
    root.set("idMax", str(ids.last))
    return etree.ElementTree(root)


def inspection_document(regions: Sequence[Region], *, part_name: str, unit: str = "mm",
                        nominal_file: str | None = None, nominal_format: str | None = None,
                        T_part_from_measured: Sequence[Sequence[float]] | None = None,
                        alignment: str = "bestfit", overall_pass: bool | None = None,
                        traceability: Traceability | None = None,
                        device: str = "scancell fringe scanner on a laser tracker",
                        decision_rule: str | None = None, overall_verdict: str | None = None
                        ) -> etree._ElementTree:
    """The inspection as a QIF results document: each region an ``OtherSurfaceFeature`` with a
    ``SurfaceProfileCharacteristic`` (its tolerance zone ``lower..upper`` as a profile
    tolerance of width ``upper - lower``, unequally disposed by ``upper``), and its measurement:
    the status (the decision rule's verdict: PASS, FAIL, INDETERMINATE where it is not
    provable), the worst deviations each way and the profile value ``2 max |dev|`` with its
    combined standard uncertainty (U / 2). The rule, the verdict and U stand in the
    measurement's Attributes. The alignment is the results' actual transform (part from
    measured)."""
    regions = list(regions)
    if not regions:
        raise QIFError("no region to write: an inspection with no toleranced region has no "
                       "characteristic for QIF")
    for r in regions:
        if r.lower_mm is None or r.upper_mm is None:
            raise QIFError(f"region {r.name!r}: QIF's surface profile needs a two-sided "
                           f"zone; it has {r.lower_mm}..{r.upper_mm}")
        if not r.lower_mm < r.upper_mm:
            raise QIFError(f"region {r.name!r}: tolerance {r.lower_mm}..{r.upper_mm} mm is "
                           f"empty")
        for v in (r.min_mm, r.max_mm, r.mean_mm, r.lower_mm, r.upper_mm):
            if not math.isfinite(v):
                raise QIFError(f"region {r.name!r}: a deviation of {v} cannot be written")
    t = traceability or Traceability()
    ids = _Ids()
    root = _root(ids, "scancell inspect")
    std_id = _standards(root, ids)
    _traceability(root, "PreInspectionTraceability", t, std_id, ids)
    _file_units(root, unit)
    dev_id = _device(root, ids, device, "robot-carried binocular fringe-projection scanner "
                                        "whose stations a laser tracker fuses")
    _product(root, ids, part_name, nominal_file, nominal_format)
    feats = _el(root, "Features")
    fdefs = _el(feats, "FeatureDefinitions", n=len(regions))
    fnoms = _el(feats, "FeatureNominals", n=len(regions))
    fitems = _el(feats, "FeatureItems", n=len(regions))
    cdefs, cnoms, citems = _characteristics(root, std_id, len(regions))
    per_region = []
    for r in regions:
        fdef, fnom, fitem = ids(), ids(), ids()
        _el(fdefs, "OtherSurfaceFeatureDefinition", id=fdef)
        n = _el(fnoms, "OtherSurfaceFeatureNominal", id=fnom)
        _el(n, "Name", r.name)
        _el(n, "FeatureDefinitionId", fdef)
        it = _el(fitems, "OtherSurfaceFeatureItem", id=fitem)
        _el(it, "FeatureNominalId", fnom)
        _el(it, "FeatureName", r.name)
        _el(_el(_el(_el(it, "DeterminationMode"), "Checked"), "CheckDetails"), "Measured")
        cdef, cnom, citem = ids(), ids(), ids()
        d = _el(cdefs, "SurfaceProfileCharacteristicDefinition", id=cdef)
        _el(d, "Name", f"profile {r.name}")
        _el(d, "ToleranceValue", r.upper_mm - r.lower_mm)
        _el(d, "OuterDisposition", r.upper_mm)
        cn = _el(cnoms, "SurfaceProfileCharacteristicNominal", id=cnom)
        _el(cn, "CharacteristicDefinitionId", cdef)
        ci = _el(citems, "SurfaceProfileCharacteristicItem", id=citem)
        _el(ci, "Name", f"profile {r.name}")
        _ids_list(ci, "FeatureItemIds", [fitem])
        _ids_list(ci, "MeasurementDeviceIds", [dev_id])
        _el(ci, "CharacteristicNominalId", cnom)
        per_region.append((r, fitem, citem))
    results = _el(_el(root, "Results"), "MeasurementResultsSet", n=1)
    mr = _el(results, "MeasurementResults", id=ids())
    _traceability(mr, "InspectionTraceability", t, None, ids)
    if t.recording:
        refs = _el(mr, "ExternalFileReferences", n=1)
        ref = _el(refs, "ExternalFileReference")
        _el(ref, "URI", t.recording if "://" in t.recording or "/" not in t.recording
            else Path(t.recording).resolve().as_uri())
        _el(_el(ref, "FileSpec"), "OtherFileSpec", "MCAP")
        _el(ref, "Description", "the scan job's recording (MCAP): every frame, tracker point "
                                "and cloud the results came from")
    mf = _el(mr, "MeasuredFeatures", n=len(regions))
    meas_ids = []
    for _, fitem, _ in per_region:
        fm = ids()
        m = _el(mf, "OtherSurfaceFeatureMeasurement", id=fm)
        _el(m, "FeatureItemId", fitem)
        meas_ids.append(fm)
    cm = _el(_el(mr, "MeasuredCharacteristics"), "CharacteristicMeasurements", n=len(regions))
    for (r, _, citem), fm in zip(per_region, meas_ids, strict=True):
        m = _el(cm, "SurfaceProfileCharacteristicMeasurement", id=ids())
        verdict = r.verdict or ("pass" if r.passed else "fail")
        attrs = [("AttributeStr", "verdict", verdict)]
        if decision_rule:
            attrs.append(("AttributeStr", "decision rule", decision_rule))
        if r.u_mm is not None:
            attrs.append(("AttributeD1", "expanded uncertainty U (k = 2), mm", r.u_mm))
        a = _el(m, "Attributes", n=len(attrs))
        for tag, name, value in attrs:
            _el(a, tag, name=name, value=_text(value))
        _el(_el(m, "Status"), "CharacteristicStatusEnum", CHARACTERISTIC_STATUS[verdict])
        _el(m, "CharacteristicItemId", citem)
        _ids_list(m, "FeatureMeasurementIds", [fm])
        value = 2.0 * max(abs(r.min_mm), abs(r.max_mm))
        if r.u_mm is None:
            _el(m, "Value", value)
        else:
            _el(m, "Value", value, combinedUncertainty=_text(r.u_mm / 2), meanError=_text(0.0))
        _el(m, "WorstPositiveDeviation", max(r.max_mm, 0.0))
        _el(m, "WorstNegativeDeviation", min(r.min_mm, 0.0))
    if T_part_from_measured is not None:
        _transform(_el(mr, "ActualTransforms", n=1), ids, T_part_from_measured,
                   f"{alignment} alignment: part from measured")
    if overall_verdict is None:
        passed = all(r.passed for r in regions) if overall_pass is None else overall_pass
        overall_verdict = "pass" if passed else "fail"
    _el(_el(mr, "InspectionStatus"), "InspectionStatusEnum", INSPECTION_STATUS[overall_verdict])
    return _finish(root, ids)


def _transform(parent: etree._Element, ids: _Ids, T: Sequence[Sequence[float]],
               name: str) -> None:
    M = [[float(v) for v in row] for row in T]
    if len(M) < 3 or any(len(row) < 4 for row in M[:3]):
        raise QIFError(f"transform {name!r}: expected a 4 x 4 matrix")
    tr = _el(parent, "Transform", id=ids())
    rot = _el(tr, "Rotation")
    for k, axis in enumerate(("XDirection", "YDirection", "ZDirection")):
        _el(rot, axis, " ".join(_text(M[i][k]) for i in range(3)))
    _el(tr, "Origin", " ".join(_text(M[i][3]) for i in range(3)))
    _el(tr, "Name", name)


def write(doc: etree._ElementTree, path: str | Path) -> None:
    """The document as UTF-8 XML with its declaration."""
    doc.write(str(path), xml_declaration=True, encoding="UTF-8", pretty_print=True)


class _SignatureResolver(etree.Resolver):
    """The XSDs import W3C XML Signature from w3.org: the copy ``signxml`` ships instead."""

    def resolve(self, url: str, pubid: str, context: Any) -> Any:
        if url and url.endswith("xmldsig-core-schema.xsd"):
            import signxml

            local = Path(signxml.__file__).parent / "schemas" / "xmldsig-core-schema.xsd"
            return self.resolve_filename(str(local), context)
        return None


_SCHEMAS: dict[Path, etree.XMLSchema] = {}


def schema(folder: str | Path) -> etree.XMLSchema:
    """The compiled QIF 3.0 schema from ``folder`` (``QIFApplications/QIFDocument.xsd``)."""
    root = Path(folder) / "QIFApplications" / "QIFDocument.xsd"
    if not root.is_file():
        raise QIFError(f"{folder}: no QIFApplications/QIFDocument.xsd (the QIF 3.0 schemas)")
    if root not in _SCHEMAS:
        parser = etree.XMLParser()
        parser.resolvers.add(_SignatureResolver())
        try:
            _SCHEMAS[root] = etree.XMLSchema(etree.parse(str(root), parser))
        except (etree.XMLSchemaParseError, etree.XMLSyntaxError, OSError) as exc:
            raise QIFError(f"{root}: the schemas do not compile: {exc}") from None
    return _SCHEMAS[root]


def validate(doc: etree._ElementTree, folder: str | Path) -> None:
    """QIFError listing the first schema violations (line: message), or nothing."""
    s = schema(folder)
    if not s.validate(doc):
        first = "; ".join(f"line {e.line}: {e.message}" for e in list(s.error_log)[:5])
        raise QIFError(f"the document is not valid QIF 3.0: {first}")


#: VDI/VDE 2634 Part 2 parameters: a one-sided limit (the figure is a range or a form: 0..MPE)
#: or two-sided (a signed error: -MPE..+MPE), and what is measured
VDI_PARAMETERS = {
    "PF": (False, "probing error, form: range of the radial distances of a sphere's points to "
                  "its least-squares sphere (VDI/VDE 2634-2, 6.2)"),
    "PS": (True, "probing error, size: measured minus calibrated diameter of a sphere "
                 "(VDI/VDE 2634-2, 6.2)"),
    "SD": (True, "sphere-spacing error: measured minus calibrated distance of the two sphere "
                 "centres of a ball bar (VDI/VDE 2634-2, 6.3)"),
    "F": (False, "flatness measurement error: range of the signed distances of a plane's "
                 "points to their least-squares plane (VDI/VDE 2634-2, 6.4)"),
}


def acceptance_document(parameters: dict[str, dict[str, Any]], *, job_id: str | None = None,
                        overall_pass: bool | None = None,
                        traceability: Traceability | None = None,
                        device: str = "scancell fringe scanner",
                        overall_verdict: str | None = None,
                        decision_rule: str = "iso14253-1") -> etree._ElementTree:
    """A VDI/VDE 2634 acceptance test as a QIF results document: each parameter (``PF``,
    ``PS``, ``SD``, ``F``, and variants such as ``SD3``) a user-defined linear characteristic
    whose tolerance is its MPE (0..MPE for a range, -MPE..+MPE for a signed error), with one
    measurement per position: its value with the test's uncertainty (``U_mm`` / 2 as
    ``combinedUncertainty``) and its status against the MPE by ``decision_rule`` (PASS, FAIL,
    INDETERMINATE where neither is proven).

    ``parameters`` as :meth:`scancell.analysis.vdi2634.AcceptanceResult.to_json` gives them:
    ``{name: {"mpe_mm", "pass", "values": [{"value_mm", "position", ...}]}}``."""
    if not parameters:
        raise QIFError("no acceptance parameter to write")
    t = traceability or Traceability(job_id=job_id)
    ids = _Ids()
    root = _root(ids, "acceptance")
    std_id = _standards(root, ids, "VDI/VDE", "2634 Part 2", "2012",
                        "Optical 3-D measuring systems: systems based on area scanning")
    _traceability(root, "PreInspectionTraceability", t, std_id, ids)
    _file_units(root, "mm")
    dev_id = _device(root, ids, device, "area-scanning optical 3-D measuring system under "
                                        "VDI/VDE 2634 Part 2 acceptance")
    rows = []
    for name, p in sorted(parameters.items()):
        base = name.rstrip("0123456789")
        if base not in VDI_PARAMETERS:
            raise QIFError(f"acceptance parameter {name!r}: not a VDI/VDE 2634-2 figure "
                           f"({', '.join(VDI_PARAMETERS)})")
        mpe = p.get("mpe_mm")
        if mpe is None or not math.isfinite(float(mpe)) or float(mpe) <= 0:
            raise QIFError(f"acceptance parameter {name}: no positive MPE ({mpe!r}); QIF "
                           f"needs the limit the value is judged against")
        values = p.get("values") or []
        if not values:
            raise QIFError(f"acceptance parameter {name}: no measured value")
        rows.append((name, base, float(mpe), values))
    cdefs, cnoms, citems = _characteristics(root, std_id, len(rows))
    items = []
    for name, base, mpe, values in rows:
        signed, what = VDI_PARAMETERS[base]
        cdef, cnom, citem = ids(), ids(), ids()
        d = _el(cdefs, "UserDefinedLinearCharacteristicDefinition", id=cdef)
        _el(d, "Name", name)
        tol = _el(d, "Tolerance")
        _el(tol, "MaxValue", mpe)
        _el(tol, "MinValue", -mpe if signed else 0.0)
        _el(tol, "DefinedAsLimit", True)
        _el(d, "WhatToMeasure", what)
        n = _el(cnoms, "UserDefinedLinearCharacteristicNominal", id=cnom)
        _el(n, "CharacteristicDefinitionId", cdef)
        _el(n, "Name", name)
        _el(n, "TargetValue", 0.0)
        ci = _el(citems, "UserDefinedLinearCharacteristicItem", id=citem)
        _el(ci, "Name", name)
        _ids_list(ci, "MeasurementDeviceIds", [dev_id])
        _el(ci, "CharacteristicNominalId", cnom)
        items.append((citem, signed, mpe, values, float(parameters[name].get("U_mm") or 0.0)))
    results = _el(_el(root, "Results"), "MeasurementResultsSet", n=1)
    mr = _el(results, "MeasurementResults", id=ids())
    _traceability(mr, "InspectionTraceability", t, None, ids)
    total = sum(len(item[3]) for item in items)
    cm = _el(_el(mr, "MeasuredCharacteristics"), "CharacteristicMeasurements", n=total)
    verdicts = []
    for citem, signed, mpe, values, U in items:
        for v in values:
            value = float(v["value_mm"])
            judged = decide(abs(value) if signed else value, U, Zone(-math.inf, mpe),
                            decision_rule)
            verdicts.append(judged)
            m = _el(cm, "UserDefinedLinearCharacteristicMeasurement", id=ids())
            _el(_el(m, "Status"), "CharacteristicStatusEnum", CHARACTERISTIC_STATUS[judged])
            _el(m, "CharacteristicItemId", citem)
            if U > 0:
                _el(m, "Value", value, combinedUncertainty=_text(U / 2), meanError=_text(0.0))
            else:
                _el(m, "Value", value)
    if overall_verdict is None:
        overall_verdict = (combine(verdicts) if overall_pass is None
                           else "pass" if overall_pass else "fail")
    _el(_el(mr, "InspectionStatus"), "InspectionStatusEnum", INSPECTION_STATUS[overall_verdict])
    return _finish(root, ids)


def regions_of(tolerances: dict[str, Any]) -> list[Region]:
    """The toleranced regions of an inspection's ``tolerances`` (``Inspection.to_json``):
    the whole part first, then each named region that holds points."""
    out = []
    overall = tolerances.get("overall")
    entries = ([("whole part", overall)] if overall else []) + [
        (str(r.get("name", f"region {k + 1}")), r)
        for k, r in enumerate(tolerances.get("regions") or [])]
    for name, r in entries:
        if not r.get("points"):
            continue
        out.append(Region(name, int(r["points"]), r.get("lower_mm"), r.get("upper_mm"),
                          float(r["min_mm"]), float(r["max_mm"]), float(r["mean_mm"]),
                          bool(r.get("pass")), str(r.get("verdict") or ""), r.get("U_mm")))
    return out


def inspection_from_json(body: dict[str, Any], traceability: Traceability | None = None
                         ) -> etree._ElementTree:
    """:func:`inspection_document` of an inspection's JSON (``scancell inspect --json``, the
    inspect worker's ``inspect/report``)."""
    tol = body.get("tolerances") or {}
    if not tol.get("overall") and not tol.get("regions"):
        raise QIFError("the inspection has no tolerance: QIF results need a toleranced "
                       "characteristic to judge (give --tolerance or --tolerances)")
    nominal = body.get("nominal") or {}
    source = nominal.get("source")
    align = body.get("alignment") or {}
    return inspection_document(
        regions_of(tol), part_name=Path(source).stem if source else "part",
        unit=str(nominal.get("unit") or "mm"), nominal_file=source,
        nominal_format=nominal_format(source) if source else None,
        T_part_from_measured=align.get("T_part_from_measured"),
        alignment=str(align.get("method", "bestfit")), overall_pass=tol.get("pass"),
        traceability=traceability, decision_rule=(tol.get("decision") or {}).get("text"),
        overall_verdict=tol.get("verdict"))


def acceptance_from_json(body: dict[str, Any]) -> etree._ElementTree:
    """:func:`acceptance_document` of an acceptance test's JSON (``scancell acceptance
    --json``, the acceptance worker's ``acceptance/report``)."""
    return acceptance_document(body.get("parameters") or {}, job_id=body.get("job_id"),
                               overall_pass=body.get("pass"), overall_verdict=body.get("verdict"),
                               decision_rule=body.get("decision_rule") or "iso14253-1")


#: where the QIF 3.0 schemas are, when no folder is given
SCHEMAS_ENV = "SCANCELL_QIF_SCHEMAS"


def schema_folder(given: str | Path | None = None) -> Path | None:
    """The schemas to validate against: ``given``, else ``$SCANCELL_QIF_SCHEMAS``, else none."""
    import os

    folder = given or os.environ.get(SCHEMAS_ENV)
    return Path(folder) if folder else None


def write_checked(doc: etree._ElementTree, path: str | Path,
                  schemas: str | Path | None = None) -> bool:
    """Validate ``doc`` against the QIF 3.0 schemas when they are known (:func:`schema_folder`)
    and only then write it, whole (a temporary file renamed): an invalid document raises
    QIFError and leaves nothing at ``path``. True when it was validated."""
    folder = schema_folder(schemas)
    if folder is not None:
        validate(doc, folder)
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = out.with_name(out.name + ".part")
    write(doc, tmp)
    tmp.replace(out)
    return folder is not None
