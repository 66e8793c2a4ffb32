"""The contract's one exception."""


class ContractError(ValueError):
    """An interface the CAN contract cannot carry (too many fields, a node ID out of range) or an
    ``interface.json`` that cannot be read; the message says which."""
