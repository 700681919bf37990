"""Stand-in for the hardware: the world model (vessels, hulls, target, sea, sensors and their noise), scenario
files, the sim bridge process (`bridge`) and the fleet launcher (`usv-fleet`, `fleet`)."""
