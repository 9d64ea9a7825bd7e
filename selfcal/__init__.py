"""selfcal: online self-calibration of wearable accelerometers.

`import selfcal` stays pure numpy/scipy; the service (FastAPI) and the BLE gateway
(bleak, bumble) are optional extras imported lazily.
"""

__version__ = "0.1.0"

#: Standard gravity in m/s^2 (used to convert recordings in m/s^2 to g).
STANDARD_GRAVITY_MPS2 = 9.80665

__all__ = ["__version__", "STANDARD_GRAVITY_MPS2"]
