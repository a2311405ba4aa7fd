// Random ids for Idempotency-Keys and multipart boundaries: crypto.randomUUID where there is one (Node, and pages
// in a secure context), else crypto.getRandomValues, which a page served over plain http on a LAN address has too.

export function randomId(prefix = ""): string {
  const c = (globalThis as any).crypto as Crypto | undefined;
  if (c?.randomUUID) return `${prefix}${c.randomUUID()}`;
  const bytes = new Uint8Array(16);
  if (c?.getRandomValues) c.getRandomValues(bytes);
  else for (let i = 0; i < bytes.length; i++) bytes[i] = Math.floor(Math.random() * 256);
  return prefix + Array.from(bytes, (b) => b.toString(16).padStart(2, "0")).join("");
}
