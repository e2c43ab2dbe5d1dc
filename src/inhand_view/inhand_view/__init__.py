"""The live view: the graph served to Foxglove and Lichtblick, and a web page of its own."""
