"""Readers for event-camera recordings (AEDAT 4.0 / 3.1 / 2.0) and recording -> scene conversion."""
