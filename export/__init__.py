"""embedrl export: trained policy -> ONNX -> frozen IR -> generated C (issue 4; not built yet)."""
