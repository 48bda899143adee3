"""Event-camera simulation: the DVS model (events) and the raw-domain ISP (blurry frames)."""
from .config import DVSConfig, ISPConfig, SensorNoise, SimConfig, load_sim_config
from .dvs import DVSSimulator, SimReport, SimulatedEvents, simulate_events

__all__ = [
    "DVSConfig", "ISPConfig", "SensorNoise", "SimConfig", "load_sim_config",
    "DVSSimulator", "SimReport", "SimulatedEvents", "simulate_events",
]
