"""embedrl HIL: CAN database, vcan provisioning and the hardware-in-the-loop harness (issue 6; not built yet)."""
