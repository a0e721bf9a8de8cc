"""The YAML-node kinds a scenario schema is declared with: how each value is checked, converted
and described, whatever the schema version.

A kind does two jobs from one declaration:
- `Kind.check` reads a composed YAML node (which keeps its line and column), converts it to SI
  units and reports what is wrong as an `Issue` at that node;
- `Kind.schema` writes the JSON Schema of the value, for an editor (`testbed schema`).

The scalar kinds are in `scalar.py`, the containers (`Nullable`, `Either`, `ListOf`, `MapOf`,
`Argv`) in `compound.py`, the mappings (`Obj`, `Tagged`, `Field`, `Section`) in `mapping.py`, and
what they all stand on (`Kind`, `Invalid`, `Context`) in `base.py`. Nothing here names a
scenario field: the concrete declaration of version 1 is the `schema_v1` package, the rules that
join fields are the `rules_*` modules the loader runs.
"""

from testbed.scenario.kinds.base import (
    BAD,
    NO_DEFAULT,
    SPELLING_CUTOFF,
    Context,
    Invalid,
    Items,
    Kind,
    child,
    describe,
    item,
    scalar_value,
)
from testbed.scenario.kinds.compound import Argv, Either, ListOf, MapOf, Nullable
from testbed.scenario.kinds.mapping import Field, Obj, Section, Tagged, mapping_pairs
from testbed.scenario.kinds.scalar import (
    MAX_RATE_BPS,
    Bool,
    Const,
    Duration,
    Enum,
    Float,
    Int,
    Percent,
    PrivateNetwork,
    Rate,
    Scalar,
    Str,
    Word,
)

__all__ = [
    "BAD",
    "MAX_RATE_BPS",
    "NO_DEFAULT",
    "SPELLING_CUTOFF",
    "Argv",
    "Bool",
    "Const",
    "Context",
    "Duration",
    "Either",
    "Enum",
    "Field",
    "Float",
    "Int",
    "Invalid",
    "Items",
    "Kind",
    "ListOf",
    "MapOf",
    "Nullable",
    "Obj",
    "Percent",
    "PrivateNetwork",
    "Rate",
    "Scalar",
    "Section",
    "Str",
    "Tagged",
    "Word",
    "child",
    "describe",
    "item",
    "mapping_pairs",
    "scalar_value",
]
