"""The vehicle's commander: arming, modes and failsafes as a pure state machine
(``machine.Commander``), its vocabulary (``types``) and its guidance (``guidance``)."""
