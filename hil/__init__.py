"""embedrl HIL: the CAN database generator, CAN sandboxes, the hardware-in-the-loop harness."""
