"""QIF 3.0 results: every document scancell writes validates against the official XSDs, and a
result QIF cannot hold is refused with a message and nothing written."""

from __future__ import annotations

import math

import pytest
from lxml import etree
from scancell.analysis import qif

from .conftest import QIF_SCHEMAS

pytestmark = pytest.mark.unit

needs_schemas = pytest.mark.skipif(
    not (QIF_SCHEMAS / "QIFApplications" / "QIFDocument.xsd").is_file(),
    reason=f"the QIF 3.0 schemas are not at {QIF_SCHEMAS} (set SCANCELL_SHARED_DATA)")

ACCEPTANCE = {"PF": {"mpe_mm": 0.2, "pass": True, "values": [
                  {"value_mm": 0.084, "position": 0}, {"value_mm": 0.076, "position": 1}]},
              "PS": {"mpe_mm": 0.05, "pass": False, "values": [
                  {"value_mm": -0.003, "position": 0}, {"value_mm": 0.061, "position": 1}]},
              "SD": {"mpe_mm": 0.1, "pass": True, "values": [{"value_mm": -0.0077,
                                                               "position": 0}]},
              "F": {"mpe_mm": 0.2, "pass": True, "values": [{"value_mm": 0.128, "position": 0}]},
              "SD3": {"mpe_mm": 0.2, "pass": True, "values": [{"value_mm": -0.019,
                                                                "position": 0}]}}


def inspection_body(**overall) -> dict:
    o = {"points": 5000, "lower_mm": -0.3, "upper_mm": 0.3, "mean_mm": 0.002, "min_mm": -0.52,
         "max_mm": 4.15, "pass": False, **overall}
    return {"nominal": {"source": "/cad/car_rear.step", "unit": "mm"},
            "alignment": {"method": "bestfit", "T_part_from_measured": [
                [1, 0, 0, -3300.0], [0, 1, 0, 0.06], [0, 0, 1, 100.2], [0, 0, 0, 1]]},
            "tolerances": {"overall": o, "pass": o["pass"], "regions": [
                {"name": "bumper", "points": 900, "lower_mm": -0.1, "upper_mm": 0.5,
                 "mean_mm": 0.01, "min_mm": -0.08, "max_mm": 0.3, "pass": True},
                {"name": "empty", "points": 0}]}}


def statuses(doc) -> list[str]:
    return [e.text for e in doc.getroot().iter(f"{{{qif.NS}}}CharacteristicStatusEnum")]


@needs_schemas
def test_an_inspection_is_valid_qif_with_each_region_judged(tmp_path):
    trace = qif.Traceability("scan_part-1", str(tmp_path / "job.mcap"),
                             {"hand_eye": "calibrate_hand_eye-7", "stereo": "stereo.yaml"})
    doc = qif.inspection_from_json(inspection_body(), trace)
    assert qif.write_checked(doc, tmp_path / "i.qif", QIF_SCHEMAS)
    back = etree.parse(str(tmp_path / "i.qif"))
    qif.validate(back, QIF_SCHEMAS)
    assert statuses(back) == ["FAIL", "PASS"]  # the region without points is left out
    text = (tmp_path / "i.qif").read_text()
    for needle in ("<ModelNumber>car_rear</ModelNumber>", "<UnitName>mm</UnitName>",
                   "<OtherDigitalModelFormat>STEP<", "<ReportNumber>scan_part-1</ReportNumber>",
                   "hand_eye calibration calibrate_hand_eye-7", "job.mcap",
                   "<ToleranceValue>0.6</ToleranceValue>", "<OuterDisposition>0.3</OuterDisposition>",
                   "<WorstPositiveDeviation>4.15</WorstPositiveDeviation>",
                   "<InspectionStatusEnum>FAIL</InspectionStatusEnum>",
                   "<Origin>-3300.0 0.06 100.2</Origin>"):
        assert needle in text, needle


@needs_schemas
def test_the_decision_rule_verdict_and_uncertainty_are_valid_qif(tmp_path):
    body = inspection_body(verdict="not provable", U_mm=0.062)
    body["tolerances"].update(verdict="not provable", decision={
        "rule": "iso14253-1", "k": 2.0, "text": "ISO 14253-1: conformance proven inside the "
                                                "tolerance less U"})
    body["tolerances"]["regions"][0].update(verdict="pass", U_mm=0.05)
    qif.write_checked(qif.inspection_from_json(body), tmp_path / "i.qif", QIF_SCHEMAS)
    back = etree.parse(str(tmp_path / "i.qif"))
    qif.validate(back, QIF_SCHEMAS)
    assert statuses(back) == ["INDETERMINATE", "PASS"]
    text = (tmp_path / "i.qif").read_text()
    for needle in ('name="decision rule" value="ISO 14253-1', 'name="verdict" value="not provable"',
                   'name="expanded uncertainty U (k = 2), mm" value="0.062"',
                   'combinedUncertainty="0.031" meanError="0.0"',
                   "<InspectionStatusEnum>UNKNOWN</InspectionStatusEnum>"):
        assert needle in text, needle


@needs_schemas
def test_an_acceptance_test_is_valid_qif_with_each_value_against_its_mpe(tmp_path):
    doc = qif.acceptance_document(ACCEPTANCE, job_id="acceptance-1", overall_pass=False)
    qif.write_checked(doc, tmp_path / "a.qif", QIF_SCHEMAS)
    back = etree.parse(str(tmp_path / "a.qif"))
    # sorted by name: F, PF x2, PS x2, SD, SD3; PS's second value is beyond its MPE
    assert statuses(back) == ["PASS", "PASS", "PASS", "PASS", "FAIL", "PASS", "PASS"]
    text = (tmp_path / "a.qif").read_text()
    assert "<Designator>2634 Part 2</Designator>" in text
    assert "<MinValue>-0.05</MinValue>" in text and "<MaxValue>0.05</MaxValue>" in text


@needs_schemas
def test_an_acceptance_test_with_its_uncertainty_is_valid_qif_and_says_what_is_not_provable(
        tmp_path):
    with_u = {k: {**v, "U_mm": 0.03} for k, v in ACCEPTANCE.items()}
    doc = qif.acceptance_document(with_u, job_id="acceptance-3", overall_verdict="not provable")
    qif.write_checked(doc, tmp_path / "a.qif", QIF_SCHEMAS)
    back = etree.parse(str(tmp_path / "a.qif"))
    # F 0.128, PF 0.084 / 0.076 inside 0.2 - 0.03; PS 0.061 within 0.05 + 0.03; SD3 0.019
    # against 0.2: proven; SD 0.0077 against 0.1: proven
    assert statuses(back) == ["PASS", "PASS", "PASS", "PASS", "INDETERMINATE", "PASS", "PASS"]
    text = (tmp_path / "a.qif").read_text()
    assert 'combinedUncertainty="0.015" meanError="0.0"' in text
    assert "<InspectionStatusEnum>UNKNOWN</InspectionStatusEnum>" in text


@needs_schemas
def test_values_near_zero_or_huge_are_written_as_decimals_without_an_exponent(tmp_path):
    # a live acceptance job measured PS = -6.68e-05 mm, which repr writes with an exponent
    # that xs:decimal refuses
    tiny = {**ACCEPTANCE, "PS": {"mpe_mm": 0.05, "pass": True, "values": [
        {"value_mm": -6.680044236873073e-05, "position": 0}, {"value_mm": 1e-7, "position": 1}]}}
    qif.write_checked(qif.acceptance_document(tiny, job_id="acceptance-2", overall_pass=True),
                      tmp_path / "a.qif", QIF_SCHEMAS)
    text = (tmp_path / "a.qif").read_text()
    assert "-0.00006680044236873073" in text and "0.0000001" in text and "e-0" not in text
    assert qif._text(1.5e22) == "15000000000000000000000" and float(qif._text(0.1)) == 0.1


def test_results_qif_cannot_hold_are_refused_and_nothing_is_written(tmp_path):
    out = tmp_path / "x.qif"
    no_tolerance = inspection_body()
    no_tolerance["tolerances"] = {"overall": None, "regions": []}
    cases = [(lambda: qif.inspection_from_json(no_tolerance), "has no tolerance"),
             (lambda: qif.inspection_from_json(inspection_body(max_mm=math.nan)),
              "deviation of nan"),
             (lambda: qif.inspection_from_json(inspection_body(upper_mm=None)),
              "two-sided zone"),
             (lambda: qif.inspection_document([], part_name="p"), "no region"),
             (lambda: qif.inspection_document(qif.regions_of(inspection_body()["tolerances"]),
                                              part_name="p", unit="furlong"),
              "length unit 'furlong'"),
             (lambda: qif.acceptance_document({"XY": ACCEPTANCE["PF"]}), "not a VDI/VDE"),
             (lambda: qif.acceptance_document({"PF": {**ACCEPTANCE["PF"], "mpe_mm": None}}),
              "no positive MPE")]
    for build, message in cases:
        with pytest.raises(qif.QIFError, match=message):
            qif.write_checked(build(), out)
        assert not out.exists()


@needs_schemas
def test_a_document_the_schemas_refuse_is_not_written(tmp_path):
    doc = qif.inspection_from_json(inspection_body())
    for e in doc.getroot().iter(f"{{{qif.NS}}}CharacteristicItemId"):
        e.text = "999"  # a reference to nothing: the schema's keyref catches it
    with pytest.raises(qif.QIFError, match=r"not valid QIF 3\.0: line .*999"):
        qif.write_checked(doc, tmp_path / "bad.qif", QIF_SCHEMAS)
    assert not list(tmp_path.iterdir())
    with pytest.raises(qif.QIFError, match=r"no QIFApplications/QIFDocument\.xsd"):
        qif.validate(doc, tmp_path)


def test_the_nominal_format_comes_from_the_step_header(tmp_path):
    ap214 = tmp_path / "a.step"
    ap214.write_text("ISO-10303-21;\nHEADER;\nFILE_SCHEMA(('AUTOMOTIVE_DESIGN { 1 0 10303 214 "
                     "1 1 1 1 }'));\nENDSEC;\n")
    assert qif.nominal_format(ap214) == "STEPAP214"
    assert qif.nominal_format(tmp_path / "b.stl") == "STL"
