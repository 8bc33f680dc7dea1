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


def object_for(od: canopen.ObjectDictionary, signal: str, role: str) -> ODVariable | None:
    """The EDS object a PDO signal maps: named like the DBC signal; CiA 402's controlword
    and statusword, and the standard targets and actual values of
    :data:`dbc.cia402.STANDARD_SIGNALS`, by index. None if the EDS has none."""
    index = ({"controlword": CONTROLWORD, "statusword": STATUSWORD}.get(role)
             or STANDARD_SIGNALS.get(signal))
    if index is not None:
        obj = od.get(index)
        return obj if isinstance(obj, ODVariable) else None
    return find_object(od, signal)
