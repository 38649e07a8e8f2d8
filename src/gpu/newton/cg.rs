//! The eliminated CG on the device-assembled Newton system.
