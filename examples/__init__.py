"""Example configurations of the appliance, installed with it as package data (see README, "Install")."""
