"""selfcal: online self-calibration of wearable accelerometers.

The public API (``__all__``), documented in the README::

    import selfcal
    rec = selfcal.read("recording.csv")                 # Recording
    cal = selfcal.calibrate(rec, model="affine9")       # Calibration (immutable)
    acc_g = cal.apply(rec.acc, temp_c=rec.temp_c, t_s=rec.t_s)
    cal.save("cal.json"); cal = selfcal.load_calibration("cal.json")
    online = selfcal.OnlineCalibrator(model="affine9")  # streaming: feed_samples / feed_poses
    report = selfcal.diagnose(rec)                      # what the base model misses

Everything else is internal. ``import selfcal`` stays pure numpy/scipy/pydantic; the
service (FastAPI) and the BLE gateway (bleak, bumble) are optional extras.
"""

__version__ = "0.1.0"

#: Standard gravity in m/s^2 (used to convert recordings in m/s^2 to g).
STANDARD_GRAVITY_MPS2 = 9.80665

from selfcal.api import Calibration, calibrate, diagnose, load_calibration, read  # noqa: E402
from selfcal.calibrator import OnlineCalibrator  # noqa: E402

__all__ = ["read", "calibrate", "Calibration", "load_calibration", "OnlineCalibrator", "diagnose"]
