"""The appliance's systemd units, installed with it as package data (see README, "Running unattended")."""
