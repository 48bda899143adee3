"""jAER's recording formats: AEDAT 2.0 (`aedat2`), AEDAT 3.1 (`aedat3`) and the chips' address layouts,
IMU scales and axes they share (`chips`)."""
