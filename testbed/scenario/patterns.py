"""The patterns that names in a scenario match (schema v1), in a module of their own that
imports nothing: the topology checks its namespace names against them without loading the
schema (`testbed down` reads a state file, not a scenario)."""

NODE_NAME_PATTERN = r"^[a-z][a-z0-9]{0,9}$"
HOST_NAME_PATTERN = r"^[a-z][a-z0-9-]{0,31}$"
IPV4_ADDRESS_PATTERN = r"^[0-9]{1,3}(\.[0-9]{1,3}){3}$"
LINK_NAME_PATTERN = r"^[a-z][a-z0-9]{0,9}-[a-z][a-z0-9]{0,9}$"
SCENARIO_NAME_PATTERN = r"^[a-z0-9][a-z0-9_-]{0,31}$"
