"""WebRTC egress: one peer connection per session, one outgoing video track, one data channel (aiortc 1.16).

- :mod:`.ice`: which local addresses are gathered (``webrtc_host_addresses`` replaces aioice's host gathering),
  which remote candidates are kept, the server's STUN, the clients' ICE servers (``Link: rel="ice-server"``) with
  TURN credentials in coturn's ``use-auth-secret`` scheme;
- :mod:`.sdp`: the offer's checks (every problem named, "SDP ...") and trickle-ICE fragments;
- :mod:`.track`: the video track: the newest rendered frame wins, aiortc's sender encodes it (in the loop's
  executor) H.264 or VP8 at the receiver's bandwidth estimate;
- :mod:`.messages`: the data channel's requests (a plain JSON pose read without ``json_format``'s walk);
- :mod:`.encoder`: the sender's encoders: aiortc's, measured per frame, H.264 with libx264 at a fast preset on one
  thread;
- :mod:`.peer`: :class:`~.peer.Peer`, an engine session with this sink (frames in from the data channel, timing
  and errors out on it), and :class:`~.peer.Peers`, the process's sessions (limits, the gauge, cleanup, drain).

The signalling routes (WHEP style) are HTTP: :mod:`service.http.webrtc`. Like the other transports this one
reaches the library only through the engine.
"""
