"""What the sensor observes: the data model and its file formats, the packed problem, the simulator."""
