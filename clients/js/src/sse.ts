// text/event-stream, parsed as the WHATWG HTML standard says (section 9.2.6): lines end in CR, LF or CRLF (a CR
// may end one chunk and its LF start the next); a blank line dispatches the event; "field: value" (one leading
// space dropped); lines starting with ':' are comments; an id with a NUL is ignored; `retry:` takes digits only;
// an event without data is not dispatched, but its id is still kept as the last event id.

export interface SseEvent {
  /** the event type ("message" when none was named) */
  event: string;
  /** the data lines joined by "\n" */
  data: string;
  /** the last event id so far (what a reconnect sends as Last-Event-ID); undefined when none was ever set */
  id?: string;
}

export class SseParser {
  lastEventId: string | undefined;
  /** the reconnection time the last `retry:` field asked for, in ms */
  retryMs: number | undefined;
  private buffer = "";
  private afterCr = false;
  private kind = "";
  private data: string[] = [];
  private idBuffer: string | undefined;

  constructor(lastEventId?: string) {
    this.lastEventId = lastEventId;
    this.idBuffer = lastEventId;
  }

  /** Feed decoded text; the events it completes. */
  feed(text: string): SseEvent[] {
    const out: SseEvent[] = [];
    let start = 0;
    for (let i = 0; i < text.length; i++) {
      const c = text.charCodeAt(i);
      if (c === 10 && this.afterCr && i === start && this.buffer === "") { // the LF of a CRLF split at a chunk end
        this.afterCr = false;
        start = i + 1;
        continue;
      }
      this.afterCr = false;
      if (c !== 10 && c !== 13) continue;
      this.line(this.buffer + text.slice(start, i), out);
      this.buffer = "";
      if (c === 13) {
        if (i + 1 < text.length) {
          if (text.charCodeAt(i + 1) === 10) i += 1;
        } else {
          this.afterCr = true;
        }
      }
      start = i + 1;
    }
    this.buffer += text.slice(start);
    return out;
  }

  private line(line: string, out: SseEvent[]): void {
    if (line === "") {
      this.lastEventId = this.idBuffer;
      if (this.data.length) out.push({ event: this.kind || "message", data: this.data.join("\n"), id: this.lastEventId });
      this.kind = "";
      this.data = [];
      return;
    }
    if (line.startsWith(":")) return;
    const colon = line.indexOf(":");
    const field = colon < 0 ? line : line.slice(0, colon);
    let value = colon < 0 ? "" : line.slice(colon + 1);
    if (value.startsWith(" ")) value = value.slice(1);
    if (field === "event") this.kind = value;
    else if (field === "data") this.data.push(value);
    else if (field === "id") {
      if (!value.includes("\0")) this.idBuffer = value;
    } else if (field === "retry" && /^\d+$/.test(value)) this.retryMs = Number(value);
  }
}
