"""The console's Viser GUI: its panels and the 3D scene."""
