//! The phone gateway: each WebSocket client (the Phone2Act Android app over rosbridge v2, roslibjs/roslibpy,
//! or the zero-install WebXR phone page) becomes a `Teleop.Stream` to the phone2act server.
