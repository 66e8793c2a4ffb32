"""An ONNX model's text made safe where it enters embedrl: names become identifiers, free text goes.

Every string an ONNX file carries is the author's: node and tensor names, doc strings, the graph's name, the
producer. :func:`safe_text` is applied where a model enters the exporter (``load_onnx``, and the ONNX the
exporter builds from an SB3 model), so the IR, the generated C, the reports and the ``policy.onnx`` an export
keeps hold only names of ``[A-Za-z0-9_]`` (:func:`embedrl.escape.identifier`, made unique by a ``_k``
suffix). Doc strings are dropped; the producer and graph name are kept as bounded safe text. The mapping is
idempotent: a model it returned maps to itself, so an export's ``policy.onnx`` read again gives the same
names and the same C. Metadata properties are left as they are: the one embedrl reads (the interface) is
validated by its own schema.
"""

from __future__ import annotations

from collections.abc import Iterable

import onnx

from embedrl.escape import c_comment, identifier

PRODUCER_LIMIT = 64
"""Characters of the producer's name and version kept."""


class _Names:
    """One namespace: each distinct text gets one identifier, distinct texts distinct identifiers."""

    def __init__(self) -> None:
        self.given: dict[str, str] = {}
        self.used: set[str] = set()

    def __call__(self, name: str) -> str:
        if not name:  # an omitted optional input stays omitted
            return name
        if name not in self.given:
            base = candidate = identifier(name)
            k = 1
            while candidate in self.used:
                candidate = f"{base}_{k}"
                k += 1
            self.used.add(candidate)
            self.given[name] = candidate
        return self.given[name]


def safe_text(model: onnx.ModelProto) -> onnx.ModelProto:
    """``model`` with identifier names and no doc strings (changed in place, and returned)."""
    values, nodes = _Names(), _Names()
    graph = model.graph
    for value in _values(graph):
        value.name = values(value.name)
        value.doc_string = ""
    for tensor in graph.initializer:
        tensor.name = values(tensor.name)
        tensor.doc_string = ""
    for sparse in graph.sparse_initializer:
        sparse.values.name = values(sparse.values.name)
    for node in graph.node:
        node.name = nodes(node.name)
        node.doc_string = ""
        node.input[:] = [values(i) for i in node.input]
        node.output[:] = [values(o) for o in node.output]
        for attribute in node.attribute:
            attribute.doc_string = ""
    model.doc_string = graph.doc_string = ""
    graph.name = identifier(graph.name)
    model.producer_name = c_comment(model.producer_name, PRODUCER_LIMIT)
    model.producer_version = c_comment(model.producer_version, PRODUCER_LIMIT)
    model.domain = identifier(model.domain) if model.domain else ""
    return model


def _values(graph: onnx.GraphProto) -> Iterable[onnx.ValueInfoProto]:
    yield from graph.input
    yield from graph.output
    yield from graph.value_info
