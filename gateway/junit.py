"""The regression gate's checks as JUnit XML, the test report CI systems display: one
test suite per run, one test case per metric, a ``failure`` for a metric beyond its limit
and an ``error`` for one that could not be compared, each with its message."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections.abc import Sequence

from gateway.gate import Check, Verdict

#: The ``type`` attribute of a failure and of an error.
FAILURE_TYPE = "regression"
ERROR_TYPE = "not comparable"


def junit_xml(checks: Sequence[Check], properties: Sequence[tuple[str, str]] = ()) -> str:
    """The XML text: ``<testsuites>`` with a ``<testsuite>`` per run (in order) holding a
    ``<testcase classname=RUN name=METRIC>`` per check; ``properties`` (name, value: the
    baseline, the tolerance file) on every suite."""
    root = ET.Element("testsuites", name="hil-gateway compare --baseline")
    by_run: dict[str, list[Check]] = {}
    for c in checks:
        by_run.setdefault(c.run, []).append(c)
    for run, cases in by_run.items():
        suite = ET.SubElement(root, "testsuite", name=f"regression gate: {run}")
        _counts(suite, cases)
        props = ET.SubElement(suite, "properties")
        for name, value in properties:
            ET.SubElement(props, "property", name=name, value=value)
        for c in cases:
            case = ET.SubElement(suite, "testcase", classname=run, name=c.limit.key,
                                 time="0")
            if c.verdict is Verdict.FAIL:
                ET.SubElement(case, "failure", message=c.message,
                              type=FAILURE_TYPE).text = c.message
            elif c.verdict is Verdict.ERROR:
                ET.SubElement(case, "error", message=c.message,
                              type=ERROR_TYPE).text = c.message
    _counts(root, list(checks))
    ET.indent(root)
    return ET.tostring(root, encoding="unicode", xml_declaration=True) + "\n"


def _counts(element: ET.Element, checks: Sequence[Check]) -> None:
    element.set("tests", str(len(checks)))
    element.set("failures", str(sum(c.verdict is Verdict.FAIL for c in checks)))
    element.set("errors", str(sum(c.verdict is Verdict.ERROR for c in checks)))
    element.set("skipped", "0")
