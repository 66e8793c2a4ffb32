"""embedrl HIL: CAN database, vcan provisioning, hardware-in-the-loop harness (issue 6; not built yet)."""
