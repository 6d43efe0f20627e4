"""Built-in sensor families (GelSight, GelSight Mini, DIGIT), each a plugin of the sensor-family hook."""
