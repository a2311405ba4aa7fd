// Typed errors: every error the service answers carries its status (code, message, field), from the REST error body
// {"error": {"code", "message", "field"}} or a stream's `error` / final `status` message.
export class BlendsplatError extends Error {
    status;
    httpStatus;
    retryAfterMs;
    constructor(status, httpStatus, retryAfterMs) {
        super(`${status.code}: ${status.message}${status.field ? ` (field ${status.field})` : ""}`);
        this.name = classNames[status.code] ?? "BlendsplatError";
        this.status = status;
        this.httpStatus = httpStatus;
        this.retryAfterMs = retryAfterMs;
    }
    get code() { return this.status.code; }
    get field() { return this.status.field; }
}
const classNames = {
    CANCELLED: "Cancelled", INVALID_ARGUMENT: "InvalidArgument", NOT_FOUND: "NotFound",
    PERMISSION_DENIED: "PermissionDenied", RESOURCE_EXHAUSTED: "ResourceExhausted",
    FAILED_PRECONDITION: "FailedPrecondition", INTERNAL: "Internal", UNAVAILABLE: "Unavailable",
    UNAUTHENTICATED: "Unauthenticated", DEADLINE_EXCEEDED: "Timeout",
};
const byHttp = {
    400: "INVALID_ARGUMENT", 401: "UNAUTHENTICATED", 403: "PERMISSION_DENIED", 404: "NOT_FOUND",
    408: "DEADLINE_EXCEEDED", 409: "FAILED_PRECONDITION", 413: "INVALID_ARGUMENT", 422: "INVALID_ARGUMENT",
    429: "RESOURCE_EXHAUSTED", 499: "CANCELLED", 503: "UNAVAILABLE",
};
/** `Retry-After` (seconds or an HTTP date) in milliseconds. */
export function retryAfterMs(value) {
    if (!value)
        return undefined;
    const seconds = Number(value);
    if (Number.isFinite(seconds))
        return Math.max(0, seconds * 1000);
    const date = Date.parse(value);
    return Number.isNaN(date) ? undefined : Math.max(0, date - Date.now());
}
/** The typed error of an HTTP error answer. */
export async function fromResponse(response) {
    const text = await response.text().catch(() => "");
    const wait = retryAfterMs(response.headers.get("retry-after"));
    try {
        const error = JSON.parse(text)?.error;
        if (error?.code) {
            return new BlendsplatError({ code: String(error.code), message: String(error.message ?? ""),
                field: String(error.field ?? "") }, response.status, wait);
        }
    }
    catch { /* not JSON: below */ }
    const code = byHttp[response.status] ?? (response.status >= 500 ? "INTERNAL" : "UNKNOWN");
    return new BlendsplatError({ code, message: text.slice(0, 200) || `HTTP ${response.status}`, field: "" }, response.status, wait);
}
/** The typed error of a stream's Status message (protobuf JSON). */
export function fromStatus(status) {
    return new BlendsplatError({ code: status.code ?? "OK", message: status.message ?? "", field: status.field ?? "",
        frameIndex: Number(status.frameIndex ?? 0) });
}
export function timeoutError(what) {
    return new BlendsplatError({ code: "DEADLINE_EXCEEDED", message: what, field: "" });
}
export function connectionError(what) {
    return new BlendsplatError({ code: "UNAVAILABLE", message: what, field: "" });
}
