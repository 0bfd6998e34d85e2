"""Images: rendering the sensor's view and detecting dots, spots, rim and corners in it."""
