"""KEY=VALUE,... changes to a settings dataclass, as the benches' --set and --mapper take them.

Each value is read as the type of the field's default; booleans take only true/false/1/0/yes/no, so a
typo is an error rather than False. Not a bench itself (scripts/bench lists [a-z]*.py only).
"""


def parse_value(text: str, default):
    """text read as the type of default; ValueError when it is not one."""
    if isinstance(default, bool):
        low = text.strip().lower()
        if low not in ("true", "false", "1", "0", "yes", "no"):
            raise ValueError(f"{text!r} is not a boolean (true/false)")
        return low in ("true", "1", "yes")
    if default is None:
        return text
    try:
        return type(default)(text)
    except ValueError:
        raise ValueError(f"{text!r} is not a {type(default).__name__}") from None


def overrides(text: str, defaults, fixed=()) -> dict:
    """'key=value,...' as {field: value} of defaults' fields (a dataclass instance); ValueError on a
    field it does not have, a field in fixed, an item that is not key=value or a value of the wrong
    kind."""
    out = {}
    for item in filter(None, text.split(",")):
        key, eq, value = item.partition("=")
        key = key.strip()
        if not eq:
            raise ValueError(f"{item!r} is not key=value")
        if not hasattr(defaults, key) or key in fixed:
            raise ValueError(f"no setting {key!r} to change here")
        out[key] = parse_value(value, getattr(defaults, key))
    return out
