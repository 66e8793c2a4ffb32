"""The contract between the simulator and a deployed policy node, derived from the policy's interface.

Both sides build on it: ``embedrl export`` writes its C into the export folder (``can/``, ``can-fd/``), so
``make -C runtime_c`` needs only the C toolchain, and ``embedrl hil`` encodes and decodes frames with the
same database. The lowest part of the export layer: it imports nothing from the rest of
``embedrl.export`` nor from the HIL package (``tests/test_architecture.py`` holds it there).

- :mod:`.interface_file`: an export's ``interface.json`` read as untrusted input;
- :mod:`.layout`: the CAN frames (IDs, bits, scales, node offsets, status and diagnosis messages);
- :mod:`.dbc`: the cantools database of that layout, the DBC text and its table;
- :mod:`.e2e`: the end-to-end protection's parameters (CRC, alive counter);
- :mod:`.glue`: the C that maps frames to the policy's observation and action vectors;
- :mod:`.sources`: every file of the node's CAN code, and the folders an export keeps them in;
- :mod:`.literals`: numbers written as C and DBC text.

``python -m embedrl.export.contract`` writes the DBC and the C, or prints the frames as a table.
"""
