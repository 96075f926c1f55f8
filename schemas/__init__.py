"""uma's public data contracts: pydantic models (``schemas.models``), the msgpack wire codec
(``schemas.codec``), the safe expression language (``schemas.expr``) and the exported JSON
Schemas (``*.json`` beside this file).

Importing this package imports nothing else, so ``schemas.expr`` stays usable from the pure
SRG code without pulling in pydantic.
"""
