"""Which object of a drive's EDS a PDO signal of its DBC maps (python-canopen's object
dictionary): the one place both the master (on line) and `profile check` (off line) ask."""

from __future__ import annotations

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable

from dbc.cia402 import CONTROLWORD, STANDARD_SIGNALS, STATUSWORD


def find_object(od: canopen.ObjectDictionary, name: str) -> ODVariable | None:
    """The EDS variable of that ParameterName (an object or a sub-index); None if none."""
    try:
        obj = od[name]
    except KeyError:
        obj = None
    if isinstance(obj, ODVariable):
        return obj
    for o in od.values():
        if isinstance(o, ODRecord | ODArray):
            for var in o.values():
                if var.name == name:
                    return var
    return None


def object_for(od: canopen.ObjectDictionary, signal: str, role: str,
               explicit: tuple[int, int] | None = None) -> ODVariable | None:
    """The EDS object a PDO signal maps: ``explicit`` (the drive profile's [objects] entry:
    index, sub-index) where given; else CiA 402's controlword and statusword, and the
    standard targets and actual values of :data:`dbc.cia402.STANDARD_SIGNALS`, by index;
    else the object named like the DBC signal. None if the EDS has none."""
    if explicit is not None:
        index, sub = explicit
        obj = od.get(index)
        if isinstance(obj, ODRecord | ODArray):
            return obj.get(sub) if sub in obj else None
        return obj if isinstance(obj, ODVariable) and sub == 0 else None
    index = ({"controlword": CONTROLWORD, "statusword": STATUSWORD}.get(role)
             or STANDARD_SIGNALS.get(signal))
    if index is not None:
        obj = od.get(index)
        return obj if isinstance(obj, ODVariable) else None
    return find_object(od, signal)
